"""Ahead-of-time compilation of several jitted programs side by side.

XLA compiles outside Python's global lock, so programs given to `compile_ahead` compile in
parallel threads, each as soon as it is traced: a run's generation step compiles while its
`init` does. Programs needed only later (`evaluate`, at the end of a run)
start compiling once the first ones are ready, so that they do not slow those down (tracing
holds the lock, and XLA's autotuning shares the GPU), and finish in the background while the
run trains.
"""

from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Any, Callable, Mapping

Programs = Mapping[str, tuple[Callable, tuple[Any, ...]]]


def compile_ahead(programs: Programs, later: Programs | None = None) -> dict[str, Future]:
    """{name: (jitted function, example arguments)} -> {name: future of its compiled program}.

    `programs` start compiling at once, side by side; `later` ones once all of `programs` are
    compiled. The arguments may be arrays or `jax.ShapeDtypeStruct`s; each compiled program
    accepts arguments of those shapes and dtypes, with the jitted function's donations.
    """
    later = later or {}
    pool = ThreadPoolExecutor(max_workers=max(len(programs) + len(later), 1),
                              thread_name_prefix="compile")
    futures = {name: pool.submit(_compile, fn, args) for name, (fn, args) in programs.items()}
    first = list(futures.values())
    futures.update({name: pool.submit(_compile, fn, args, after=first)
                    for name, (fn, args) in later.items()})
    pool.shutdown(wait=False)
    return futures


def _compile(fn: Callable, args: tuple, after: list[Future] = ()):
    wait(after)
    return fn.lower(*args).compile()

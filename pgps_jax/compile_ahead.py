"""Ahead-of-time compilation of several jitted programs side by side.

XLA compiles outside Python's global lock, so programs given to `compile_ahead` compile in
parallel threads, each as soon as it is traced: a run's generation step compiles while its
`init` does, and the programs it needs only at the end (`evaluate`, `finish_evaluation`)
compile in the background while it trains.
"""

from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Mapping


def compile_ahead(programs: Mapping[str, tuple[Callable, tuple[Any, ...]]]
                  ) -> dict[str, Future]:
    """{name: (jitted function, example arguments)} -> {name: future of its compiled program}.

    The arguments may be arrays or `jax.ShapeDtypeStruct`s; each compiled program accepts
    arguments of those shapes and dtypes, with the jitted function's donations.
    """
    pool = ThreadPoolExecutor(max_workers=max(len(programs), 1),
                              thread_name_prefix="compile")
    futures = {name: pool.submit(lambda fn=fn, args=args: fn.lower(*args).compile())
               for name, (fn, args) in programs.items()}
    pool.shutdown(wait=False)
    return futures

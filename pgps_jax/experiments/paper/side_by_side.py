"""Cells in flight side by side: each in a process of its own, placed on the GPUs in turn.

One cell's generation is a chain of small kernels that leaves a GPU mostly idle; several cells
in separate processes fill it (better still under CUDA's MPS daemon, which lets their kernels
run at once). With `concurrent` slots over G visible GPUs, slot s runs its cells on GPU
s mod G with the whole of that GPU's memory shared by the slots placed there; on a CPU every
slot uses the host. A cell in a process of its own computes what it computes in the command's
own process (same seed, same machine, same result).

The parent hands a child its cell and budget on stdin and reads one JSON line per generation
on its stdout (`python -m pgps_jax.experiments.paper.side_by_side` is the child's side).
"""

import json
import math
import os
import pathlib
import pickle
import signal
import subprocess
import sys
import threading
from typing import Callable, Optional, Sequence

from pgps_jax.cli.errors import EXIT_INTERRUPTED, EXIT_OK, RunFailed, report
from pgps_jax.experiments.paper.grid import Cell
from pgps_jax.experiments.paper.runner import RESULT, Budget, run_cell

MEMORY_IN_USE = 0.9
"""The share of a GPU's memory that the processes placed on it take in all."""


def placements(concurrent: int, platform: str, devices: int,
               visible: Optional[str]) -> list[dict]:
    """Per slot, the environment variables that place its processes: on a GPU machine, the
    one GPU it sees (of CUDA_VISIBLE_DEVICES `visible`, or all) and its share of that GPU's
    memory (unless preallocation is turned off); none elsewhere."""
    if platform != "gpu":
        return [{} for _ in range(concurrent)]
    ids = visible.split(",") if visible else [str(i) for i in range(devices)]
    per_gpu = math.ceil(concurrent / len(ids))
    return [{"CUDA_VISIBLE_DEVICES": ids[slot % len(ids)],
             "XLA_PYTHON_CLIENT_MEM_FRACTION": f"{MEMORY_IN_USE / per_gpu:.3f}"}
            for slot in range(concurrent)]


def run_side_by_side(experiment: str, budget: Budget, cells: Sequence[Cell],
                     directory_of: Callable[[Cell], pathlib.Path], slots: list[dict],
                     environ: dict, on_progress: Callable[[Cell, int, list], None]) -> list[dict]:
    """Runs `cells` with len(slots) of them at a time, each in a child process with `environ`
    and its slot's variables; `on_progress(cell, generation, env_steps)` after each
    generation of any. Returns the results in the order of `cells`; RunFailed naming every
    cell that failed (after the others have finished)."""
    jobs = list(enumerate(cells))
    queue = jobs[len(slots):]  # slot s starts cell s, then takes the next as it comes free
    results, failures, children = [None] * len(cells), [], []
    stopping = threading.Event()
    lock = threading.Lock()

    def work(slot: dict, job) -> None:
        while job is not None:
            index, cell = job
            with lock:
                if stopping.is_set():
                    return
                child = subprocess.Popen(
                    [sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**environ, **slot})
                children.append(child)
            try:
                outcome = _follow(child, cell, directory_of(cell), budget,
                                  lambda *done: _locked(lock, on_progress, cell, *done))
            except Exception as e:  # the parent's side failed: the child must not run on
                child.kill()
                child.wait()
                outcome = f"{type(e).__name__}: {e}"
            with lock:
                if isinstance(outcome, dict):
                    results[index] = outcome
                else:
                    failures.append(f"{cell.task} {cell.config}: {outcome}")
                job = queue.pop(0) if queue else None

    threads = [threading.Thread(target=work, args=(slot, job), daemon=True)
               for slot, job in zip(slots, jobs)]
    for thread in threads:
        thread.start()
    try:
        for thread in threads:
            thread.join()
    except KeyboardInterrupt:  # each child stops; its cell continues from its checkpoint
        with lock:
            stopping.set()
            for child in children:
                if child.poll() is None:
                    child.send_signal(signal.SIGINT)
        for child in children:
            child.wait()
        raise
    if failures:
        raise RunFailed(f"{experiment}: {len(failures)} cell(s) failed: " + "; ".join(failures))
    return results


def _locked(lock: threading.Lock, function: Callable, *args) -> None:
    with lock:
        function(*args)


def _follow(child: subprocess.Popen, cell: Cell, directory: pathlib.Path, budget: Budget,
            on_progress: Callable[[int, list], None]):
    """Hands `cell` to `child` and follows it to its end: its result, or what its error
    line said."""
    errors = []
    reader = threading.Thread(target=lambda: errors.append(child.stderr.read()))
    reader.start()
    child.stdin.write(pickle.dumps((cell, directory, budget)))
    child.stdin.close()
    for line in child.stdout:
        if line.startswith(b"{"):  # a generation's line, not a library's print
            done = json.loads(line)
            on_progress(done["generation"], done["env_steps"])
    reader.join()
    if child.wait() == 0:
        return json.loads((directory / RESULT).read_text())
    said = [line for line in errors[0].decode(errors="replace").splitlines()
            if line.startswith("error: ")]
    return said[0][len("error: "):] if said else f"exit status {child.returncode}"


def _child() -> int:
    """Runs the cell handed over on stdin; one JSON line per generation on stdout."""
    cell, directory, budget = pickle.loads(sys.stdin.buffer.read())

    def progress(generation, env_steps) -> None:
        print(json.dumps({"generation": generation, "env_steps": env_steps.tolist()}),
              flush=True)

    def body() -> int:
        run_cell(cell, directory, budget, progress)
        return EXIT_OK
    try:
        return report(body)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(_child())

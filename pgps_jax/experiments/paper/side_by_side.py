"""Cells in flight side by side: each in a process of its own, placed on the GPUs in turn; a
cell run in parts (`runner.parts`) as one process per part.

One cell's generation is a chain of small kernels that leaves a GPU mostly idle; several cells
in separate processes fill it (better still under CUDA's MPS daemon, which lets their kernels
run at once). With `concurrent` slots over G visible GPUs, slot s runs its cells on GPU
s mod G, the slots placed on a GPU sharing `memory_share` of its memory equally; on a CPU
every slot uses the host. On the CPU or one GPU a cell in a process of its own computes what
it computes in the command's own process (same seed, same machine, same result); with several
GPUs the command's own process splits a cell's seeds over all of them and a child's over its
one, so their last bits can differ and a checkpoint of one continues only in the other's way.

The parent hands a child its cell, its seeds and the budget on stdin and reads its progress
on its stdout, one `PROGRESS` line per generation (`python -m
pgps_jax.experiments.paper.side_by_side` is the child's side); each writes its results where
the cell run in turn would. Each child has a session of its own, so that Ctrl-C (or SIGTERM
to the parent) reaches it once, from the parent: it stops after its generation under way
with a checkpoint, even if the parent is gone by then.
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

from pgps_jax.cli.errors import (EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, RunFailed, UsageError,
                                  report)
from pgps_jax.cli.stop_request import sigterm_as_ctrl_c
from pgps_jax.experiments.paper.grid import Cell
from pgps_jax.experiments.paper.runner import Budget, Seeds, run_cell

MEMORY_IN_USE = 0.9
"""The share of a GPU's memory that the processes placed on it take in all, unless the
command is given a share of its own (`memory_share`)."""
MEMORY_FRACTION = "XLA_CLIENT_MEM_FRACTION"
"""JAX's variable of a process's share of its GPU's memory (its older name, which it refuses
beside this one, is dropped from the children's environment)."""
MEMORY_FRACTION_OLD = "XLA_PYTHON_CLIENT_MEM_FRACTION"
PROGRESS = b"pgps-progress "
"""The prefix of a child's progress lines: a JSON object of generation and env steps."""


def memory_share(environ: dict) -> float:
    """The share of each GPU's memory that the slots placed on it divide between them: the
    command's own, where its environment sets JAX's memory fraction (`MEMORY_FRACTION` or
    its older name, to leave room for other processes on the GPUs), else `MEMORY_IN_USE`."""
    for name in (MEMORY_FRACTION, MEMORY_FRACTION_OLD):
        if name in environ:
            try:
                share = float(environ[name])
            except ValueError:
                share = math.nan
            if not 0 < share <= 1:
                raise UsageError(f"{name}={environ[name]!r}: the share of each GPU's memory that "
                                 "the processes side by side divide is a number in (0, 1]")
            return share
    return MEMORY_IN_USE


def placements(concurrent: int, platform: str, devices: int, visible: Optional[str],
               memory: float = MEMORY_IN_USE) -> list[dict]:
    """Per slot, the environment variables that place its processes: on a GPU machine, the
    one GPU it sees (of CUDA_VISIBLE_DEVICES `visible`, or all) and its equal part of the
    `memory` share of that GPU's memory (`memory_share`); none elsewhere."""
    if platform != "gpu":
        return [{} for _ in range(concurrent)]
    ids = visible.split(",") if visible else [str(i) for i in range(devices)]
    per_gpu = math.ceil(concurrent / len(ids))
    return [{"CUDA_VISIBLE_DEVICES": ids[slot % len(ids)],
             MEMORY_FRACTION: f"{memory / per_gpu:.3f}"}
            for slot in range(concurrent)]


def run_side_by_side(experiment: str, budget: Budget, units: Sequence[tuple[Cell, Seeds]],
                     directory_of: Callable[[Cell], pathlib.Path], slots: list[dict],
                     environ: dict, on_progress: Callable[[Cell, Seeds, int, list], None]
                     ) -> None:
    """Runs `units` (a cell and its seeds: the whole cell or a part, `runner.parts`) with
    len(slots) of them at a time, each in a child process with `environ` and its slot's
    variables; `on_progress(cell, seeds, generation, env_steps)` after each generation of any
    (and once for one that was done already). RunFailed naming every one that failed, with
    what it said, once the others have finished (their results are written)."""
    jobs = list(units)
    queue = jobs[len(slots):]  # slot s starts unit s, then takes the next as it comes free
    failures, children = [], []
    lock, stopping = threading.Lock(), threading.Event()
    inherited = {k: v for k, v in environ.items() if k != MEMORY_FRACTION_OLD}

    def work(slot: dict, job) -> None:
        while job is not None:
            cell, part = job
            child = None
            try:
                with lock:
                    if stopping.is_set():
                        return
                    child = subprocess.Popen(
                        [sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                        env={**inherited, **slot}, start_new_session=True)
                    children.append(child)
                failed = _follow(child, cell, part, directory_of(cell), budget,
                                 lambda *done: _locked(lock, on_progress, cell, part, *done))
            except Exception as e:  # the parent's side failed: the child must not run on
                if child is not None and child.poll() is None:
                    child.kill()
                    child.wait()
                failed = f"{type(e).__name__}: {e}"
            with lock:
                if failed is not None:
                    failures.append(f"{cell.task} {cell.config}"
                                    f"{'' if part.whole else f' seeds {part.first}-{part.last}'}: "
                                    f"{failed}")
                job = queue.pop(0) if queue else None

    threads = [threading.Thread(target=work, args=(slot, job), daemon=True)
               for slot, job in zip(slots, jobs)]
    for thread in threads:
        thread.start()
    try:
        with sigterm_as_ctrl_c():
            for thread in threads:
                thread.join()
    except KeyboardInterrupt:  # each child stops; its cell continues from its checkpoint
        print("stopping: each program writes a checkpoint after its generation under way",
              file=sys.stderr)
        with lock:
            stopping.set()
            for child in children:
                if child.poll() is None:
                    child.send_signal(signal.SIGTERM)  # a stop, also after one of its own
        for child in children:
            child.wait()
        raise
    if failures:
        raise RunFailed(f"{experiment}: {len(failures)} of {len(units)} program(s) failed: "
                        + "; ".join(failures))


def _locked(lock: threading.Lock, function: Callable, *args) -> None:
    with lock:
        function(*args)


def _follow(child: subprocess.Popen, cell: Cell, part: Seeds, directory: pathlib.Path,
            budget: Budget, on_progress: Callable[[int, list], None]) -> Optional[str]:
    """Hands `cell`'s seeds `part` to `child` and follows it to its end: None if it
    succeeded, else what it said on stderr (its `error:` line and the next lines, else its
    last lines)."""
    errors = []
    reader = threading.Thread(target=lambda: errors.append(child.stderr.read()))
    reader.start()
    try:
        child.stdin.write(pickle.dumps((cell, part, directory, budget)))
        child.stdin.close()
    except BrokenPipeError:  # it ended before reading: its stderr says why
        pass
    for line in child.stdout:
        if line.startswith(PROGRESS):
            done = json.loads(line[len(PROGRESS):])
            on_progress(done["generation"], done["env_steps"])
    reader.join()
    if child.wait() == 0:
        return None
    lines = errors[0].decode(errors="replace").rstrip().splitlines()
    said = [i for i, line in enumerate(lines) if line.startswith("error: ")]
    if said:  # with its first lines of detail (a list of differing settings, say)
        return " ".join(line.strip() for line in lines[said[0]:said[0] + 4])[len("error: "):]
    return f"exit status {child.returncode}: " + " | ".join(lines[-3:])


def _child() -> int:
    """Runs the cell's seeds handed over on stdin; a `PROGRESS` line per generation on
    stdout."""
    cell, part, directory, budget = pickle.loads(sys.stdin.buffer.read())

    def progress(generation, env_steps) -> None:
        try:
            sys.stdout.buffer.write(PROGRESS + json.dumps(
                {"generation": int(generation), "env_steps": [int(s) for s in env_steps]}
            ).encode() + b"\n")
            sys.stdout.buffer.flush()
        except BrokenPipeError:  # the command is gone: the cell goes on to its checkpoint
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())

    def body() -> int:
        result = run_cell(cell, directory, budget, progress, part)
        progress(result["generations"], result["env_steps"])  # a cell done before, too
        return EXIT_OK
    try:
        with sigterm_as_ctrl_c():
            return report(body)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except Exception as e:  # one line for the parent to name (an out-of-memory error, say)
        print(f"error: {type(e).__name__}: {e}", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(_child())

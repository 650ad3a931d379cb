"""Helpers of the training CLI tests: run `python -m pgps_jax.<module>`, read its outputs."""

import contextlib
import csv
import importlib
import io
import logging
import os
import pathlib
import struct
import subprocess
import sys
import time

REPO = pathlib.Path(__file__).resolve().parent.parent

TINY = ("env=point", "seed=1", "total_steps=3000", "eval_every=400", "checkpoint_every=3",
        "checkpoint_every_s=null", "progress=false")
"""A run of ~25 short generations of a tiny PGPS on the point mass, checkpointed every three
generations and not by the clock."""



def tiny(*overrides: str) -> list[str]:
    """TINY with `overrides` replacing settings of the same key."""
    merged = {a.split("=", 1)[0]: a for a in TINY}
    merged.update({a.split("=", 1)[0]: a for a in overrides})
    return list(merged.values())


HOST_COLUMNS = ("steps_per_s", "wall_time_s")

FAST_COMPILE_FLAGS = ("--xla_backend_optimization_level=0",
                      "--xla_llvm_disable_expensive_passes=true",
                      "--xla_cpu_use_fusion_emitters=false")
"""XLA flags that compile in a third of the CPU time (a reduced hopper run: 47 s instead of
98 on 2 cores) and run the tests' small programs as fast: for the tests and their CLI
subprocesses only, never a user's run."""


def with_fast_compile_flags(xla_flags: str) -> str:
    """`xla_flags` with `FAST_COMPILE_FLAGS` added, if this JAX's XLA accepts them (it stops
    the process at its first computation on an unknown flag): checked once, in a
    subprocess; unchanged if all are there already or they are refused."""
    flags = xla_flags.split()
    if all(f in flags for f in FAST_COMPILE_FLAGS):
        return xla_flags
    wanted = " ".join([*flags, *FAST_COMPILE_FLAGS])
    compute = "import jax; jax.numpy.zeros(1).block_until_ready()"
    probe = subprocess.run([sys.executable, "-c", compute], capture_output=True, timeout=120,
                           env={**os.environ, "XLA_FLAGS": wanted})
    return wanted if probe.returncode == 0 else xla_flags


def cli_env(cache_dir: pathlib.Path) -> dict:
    """The environment of a CLI subprocess: the test process's (with its XLA flags), on the
    CPU, and a persistent compilation cache shared by the test's subprocesses (the same
    program compiles to the same executable)."""
    env = dict(os.environ)
    env.update(JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(cache_dir),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", PYTHONUNBUFFERED="1")
    return env


def run(module: str, args, cache_dir: pathlib.Path, cwd: pathlib.Path,
        timeout: float = 600, **environ: str) -> subprocess.CompletedProcess:
    """`python -m pgps_jax.<module> <args>`, with `environ` added to its environment."""
    return subprocess.run([sys.executable, "-m", f"pgps_jax.{module}", *args], cwd=cwd,
                          env={**cli_env(cache_dir), **environ}, capture_output=True, text=True,
                          timeout=timeout)


def run_here(module: str, args, cwd: pathlib.Path) -> subprocess.CompletedProcess:
    """`python -m pgps_jax.<module> <args>` run in this process: its `main` with `args` as
    the command line, in `cwd`, on the CPU (as `run`'s subprocesses), with stdout and stderr
    captured. It saves a Python start-up, and a second run of the same settings in this
    process reuses the first one's compiled programs (`pgps_jax.cli.loop`)."""
    import jax
    main = importlib.import_module(f"pgps_jax.{module}").main
    out, err = io.StringIO(), io.StringIO()
    argv, here = sys.argv, os.getcwd()
    handlers = logging.root.handlers[:]  # Hydra sets up logging to the streams of the moment
    device = jax.config.jax_default_device
    # Hydra's logging set-up closes every handler, and absl's closes its stream unless that is
    # the sys.stderr of the moment: pytest's capture, were it not pointed at ours meanwhile
    absl = sys.modules.get("absl.logging")
    absl_handler = absl.get_absl_handler().python_handler if absl else None
    absl_stream = absl_handler.stream if absl_handler else None
    sys.argv = [f"pgps_jax.{module}", *args]
    try:
        if absl_handler:
            absl_handler.stream = err
        # global, not a context: the programs compile in threads of their own
        jax.config.update("jax_default_device", jax.devices("cpu")[0])
        os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main() or 0
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
    finally:
        sys.argv = argv
        os.chdir(here)
        jax.config.update("jax_default_device", device)
        logging.root.handlers[:] = handlers
        if absl_handler:
            absl_handler.stream = absl_stream
    return subprocess.CompletedProcess([module, *args], code, out.getvalue(), err.getvalue())


def start(module: str, args, cache_dir: pathlib.Path, cwd: pathlib.Path,
          log: pathlib.Path) -> subprocess.Popen:
    """A CLI process in the background; stdout and stderr go to `log`."""
    out = open(log, "w")
    return subprocess.Popen([sys.executable, "-m", f"pgps_jax.{module}", *args], cwd=cwd,
                            env=cli_env(cache_dir), stdout=out, stderr=subprocess.STDOUT)


def read_csv(path: pathlib.Path) -> tuple[list[str], list[dict]]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames), list(reader)


def deterministic(rows: list[dict]) -> list[dict]:
    """metrics.csv rows without the host-measured columns."""
    return [{k: v for k, v in r.items() if k not in HOST_COLUMNS} for r in rows]


def checkpoint_steps(run_dir: pathlib.Path) -> list[int]:
    directory = run_dir / "checkpoints"
    if not directory.exists():
        return []
    return sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit())


def leftovers(run_dir: pathlib.Path) -> list[str]:
    """Temporary files or directories: what an interrupted write would leave behind."""
    return [str(p) for p in run_dir.rglob("*") if "tmp" in p.name.lower()]


def wait_until(predicate, process: subprocess.Popen, timeout: float = 300,
               poll: float = 0.02) -> None:
    """Polls `predicate` every `poll` s until true; fails if the process ends or time runs out
    first."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if process.poll() is not None:
            raise AssertionError(f"the process ended (status {process.returncode}) too early")
        if time.monotonic() > deadline:
            process.kill()
            raise AssertionError("timed out waiting for the process")
        time.sleep(poll)


def data_rows(path: pathlib.Path) -> int:
    """Complete data lines written so far (0 if the file does not exist yet)."""
    if not path.exists():
        return 0
    return max(0, path.read_bytes().count(b"\n") - 1)


def tensorboard_tags(directory: pathlib.Path) -> set[str]:
    """Scalar tags in the TensorBoard event files (TFRecord framing, Event protos)."""
    from tensorboardX.proto import event_pb2
    tags = set()
    for path in directory.glob("events.out.tfevents.*"):
        data = path.read_bytes()
        offset = 0
        while offset + 12 <= len(data):
            (length,) = struct.unpack("<Q", data[offset:offset + 8])
            record = data[offset + 12:offset + 12 + length]
            offset += 12 + length + 4
            event = event_pb2.Event.FromString(record)
            tags.update(v.tag for v in event.summary.value)
    return tags

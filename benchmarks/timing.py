"""Timing of jitted functions and the provenance of a measurement, shared by the benchmarks."""

import dataclasses
import os
import pathlib
import subprocess
import tempfile
import time
from typing import Optional

import jax
import numpy as np


def timed(fn, *args, repeats=5):
    """(seconds of the first call = compile + run, median seconds of later calls)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start, median_seconds(fn, *args, repeats=repeats)


def repeated_seconds(fn, *args, repeats=5) -> list[float]:
    """Seconds of each of `repeats` calls of `fn(*args)`, each to the end of its outputs'
    computation (`fn` already compiled and run once)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return times


def median_seconds(fn, *args, repeats=5) -> float:
    """Median of `repeated_seconds`."""
    return float(np.median(repeated_seconds(fn, *args, repeats=repeats)))


def results_path(given: Optional[str], default: str, smoke: bool) -> pathlib.Path:
    """Where a benchmark writes: `given` (its --out), else `default`, the committed result
    under benchmarks/results/, or for a --smoke check the same file name in a temporary
    directory, so that checking a script never overwrites a measurement."""
    if given is not None:
        return pathlib.Path(given)
    if smoke:
        return pathlib.Path(tempfile.gettempdir()) / "pgps_jax_smoke" / pathlib.Path(default).name
    return pathlib.Path(default)


def provenance() -> dict:
    """The device kind, JAX version, commit and `XLA_FLAGS` a measurement is taken with (the
    commit followed by "+changes" where the package or the benchmarks differ from it)."""
    root = pathlib.Path(__file__).resolve().parents[1]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=root).stdout.strip()
    status = subprocess.run(["git", "status", "--porcelain", "-z", "--", "pgps_jax",
                             "benchmarks"], capture_output=True, text=True, cwd=root).stdout
    paths = [entry[3:] if len(entry) > 3 and entry[2] == " " else entry  # a rename's source
             for entry in status.split("\0") if entry]
    if commit and any(not path.startswith("benchmarks/results/") for path in paths):
        commit += "+changes"
    return {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "commit": commit,
            "xla_flags": os.environ.get("XLA_FLAGS", "")}


def physics_record(env) -> dict:
    """The physics `env` steps with, its start pose and its platform-dependent switches
    resolved as a step resolves them (`physics.resolved`): what a measurement ran on."""
    from pgps_jax.envs import physics
    return {"start_pose": env.start_pose,
            **dataclasses.asdict(physics.resolved(env.physics, env.mjx_model))}

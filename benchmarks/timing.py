"""Timing of jitted functions and the provenance of a measurement, shared by the benchmarks."""

import subprocess
import time

import jax
import numpy as np


def timed(fn, *args, repeats=5):
    """(seconds of the first call = compile + run, median seconds of later calls)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return first, float(np.median(times))


def provenance() -> dict:
    """The device kind, JAX version and commit a measurement is taken with (the commit
    followed by "+changes" where the package or the benchmarks differ from it)."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    changed = subprocess.run(["git", "status", "--porcelain", "--", "pgps_jax", "benchmarks"],
                             capture_output=True, text=True).stdout
    if commit and any(not line[3:].startswith("benchmarks/results")
                      for line in changed.splitlines()):
        commit += "+changes"
    return {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "commit": commit}

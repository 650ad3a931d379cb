"""Timing of jitted functions, shared by the benchmarks."""

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

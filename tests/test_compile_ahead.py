"""Tests for pgps_jax.compile_ahead: programs compile side by side, `later` ones after them."""

import os
import subprocess
import sys
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax.compile_ahead import compile_ahead


class _Program:
    """Stands in for a jitted function; its `compile` logs when it starts and ends."""

    def __init__(self, name, log, lock, seconds=0.2):
        self.name, self.log, self.lock, self.seconds = name, log, lock, seconds

    def lower(self, *args):
        return self

    def compile(self):
        with self.lock:
            self.log.append(("start", self.name))
        time.sleep(self.seconds)
        with self.lock:
            self.log.append(("end", self.name))
        return self.name


def test_first_programs_compile_side_by_side_and_later_ones_after_them():
    log, lock = [], threading.Lock()
    futures = compile_ahead({n: (_Program(n, log, lock), ()) for n in ("a", "b")},
                            later={n: (_Program(n, log, lock), ()) for n in ("c", "d")})
    assert {name: f.result() for name, f in futures.items()} == {n: n for n in "abcd"}
    index = {event: i for i, event in enumerate(log)}
    first_end = min(index["end", "a"], index["end", "b"])
    assert index["start", "a"] < first_end and index["start", "b"] < first_end
    for name in "cd":
        assert index["start", name] > max(index["end", "a"], index["end", "b"])
    assert index["start", "c"] < index["end", "d"] and index["start", "d"] < index["end", "c"]


def test_compiled_program_computes_what_jit_does():
    fn = jax.jit(lambda x: jnp.sin(x) * 2)
    x = jnp.arange(3.0)
    futures = compile_ahead({}, later={"f": (fn, (jax.ShapeDtypeStruct((3,), jnp.float32),))})
    np.testing.assert_array_equal(futures["f"].result()(x), fn(x))


_CHILD = """
import os, sys
from pgps_jax import train, trainer  # the CLI's modules: importing them starts no backend
from pgps_jax.envs import make_env
from pgps_jax.compile_ahead import compile_kernels_in_parallel
os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
compile_kernels_in_parallel(int(sys.argv[1]))
import jax
print(jax.device_count(), os.environ["XLA_FLAGS"].strip(), sep="|")
"""


def _flags_in_child(xla_flags: str, threads: int) -> tuple[str, str]:
    """(devices JAX sees, XLA_FLAGS) in a fresh process that imports the CLI's modules, then
    asks for 2 CPU devices and `threads` compile threads through XLA_FLAGS."""
    env = {**os.environ, "XLA_FLAGS": xla_flags, "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", _CHILD, str(threads)], env=env, check=True,
                         capture_output=True, text=True).stdout.strip().splitlines()[-1]
    return tuple(out.split("|"))


def test_parallel_compilation_flag_is_added_before_the_backend_starts():
    devices, flags = _flags_in_child("", 3)
    assert devices == "2"          # flags set after importing the CLI still take effect
    assert flags.split() == ["--xla_force_host_platform_device_count=2",
                             "--xla_gpu_force_compilation_parallelism=3"]


def test_parallel_compilation_keeps_a_parallelism_already_set():
    _, flags = _flags_in_child("--xla_gpu_force_compilation_parallelism=1", 3)
    assert flags.split() == ["--xla_gpu_force_compilation_parallelism=1",
                             "--xla_force_host_platform_device_count=2"]

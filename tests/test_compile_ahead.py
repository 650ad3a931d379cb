"""Tests for pgps_jax.cli.compile_ahead: programs compile side by side, `later` ones after them."""

import threading
import time

import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax.cli.compile_ahead import compile_ahead


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

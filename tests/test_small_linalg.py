"""Tests for pgps_jax.envs.mjx_rewrites.small_linalg: written-out Cholesky / triangular solves
and the rewrite of MJX's physics step that uses them."""

import functools
import itertools

import jax
from jax.extend import core
import jax.numpy as jnp
from mujoco import mjx
import numpy as np
import pytest

from pgps_jax.envs import make_env, physics
from pgps_jax.envs.mjx_rewrites import small_linalg
from pgps_jax.envs.mjx_rewrites.rewrite import rewrite

RNG = np.random.default_rng(0)


def _spd(n, batch=5):
    x = RNG.normal(size=(batch, n, n))
    return (x @ np.swapaxes(x, -1, -2) + n * np.eye(n)).astype(np.float32)


def _primitives(closed: core.ClosedJaxpr) -> set[str]:
    """Names of every primitive in `closed`, its loops and its called functions."""
    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            yield eqn.primitive.name
            for sub in core.jaxprs_in_params(eqn.params):
                yield from walk(sub)
    return set(walk(closed.jaxpr))


@pytest.mark.parametrize("n", [1, 2, 5, 9])
def test_cholesky_matches_numpy(n):
    a = _spd(n)
    factor = np.asarray(small_linalg.cholesky(jnp.asarray(a)))
    np.testing.assert_allclose(factor, np.linalg.cholesky(a.astype(np.float64)),
                               rtol=1e-5, atol=1e-5)
    assert (np.triu(factor, 1) == 0).all()


def test_cholesky_reads_only_the_lower_triangle():
    a = _spd(4)
    upper_garbage = a + np.triu(RNG.normal(size=a.shape), 1).astype(np.float32)
    np.testing.assert_array_equal(small_linalg.cholesky(jnp.asarray(upper_garbage)),
                                  small_linalg.cholesky(jnp.asarray(a)))


def test_cholesky_of_an_indefinite_matrix_is_nan_like_jax():
    a = _spd(3)
    a[1] = np.diag([1.0, -1.0, 1.0])
    factor = np.asarray(small_linalg.cholesky(jnp.asarray(a)))
    np.testing.assert_array_equal(factor[1], np.asarray(jnp.linalg.cholesky(a[1])))
    assert np.isnan(np.tril(factor[1])[np.tri(3, dtype=bool)]).all()
    assert np.isfinite(factor[[0, 2]]).all()


@pytest.mark.parametrize("left_side,lower,transpose_a,unit_diagonal",
                         list(itertools.product([True, False], repeat=4)))
def test_triangular_solve_solves_op_a(left_side, lower, transpose_a, unit_diagonal):
    """Every variant solves op(A) X = B or X op(A) = B, ignoring A's other triangle."""
    n, k = 6, 3
    factor = np.linalg.cholesky(_spd(n).astype(np.float64))
    a = factor if lower else np.swapaxes(factor, -1, -2)
    b = RNG.normal(size=(5, n, k) if left_side else (5, k, n))
    noise = RNG.normal(size=a.shape)
    other_triangle = np.triu(noise, 1) if lower else np.tril(noise, -1)
    x = np.asarray(small_linalg.triangular_solve(
        jnp.asarray(a + other_triangle, jnp.float32), jnp.asarray(b, jnp.float32), left_side=left_side,
        lower=lower, transpose_a=transpose_a, conjugate_a=False, unit_diagonal=unit_diagonal))
    used = np.tril(a) if lower else np.triu(a)
    if unit_diagonal:
        used = used - np.eye(n) * np.diagonal(used, axis1=-2, axis2=-1)[..., None] + np.eye(n)
    op_a = np.swapaxes(used, -1, -2) if transpose_a else used
    np.testing.assert_allclose(op_a @ x if left_side else x @ op_a, b, rtol=1e-4, atol=1e-4)


def test_written_out_function_has_no_small_linalg_primitives():
    def solve(a, b):
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b)

    def in_a_loop(a, b):      # inside a while loop and a jitted function
        return jax.lax.fori_loop(0, 2, lambda _, x: jax.jit(solve)(a, x), b)

    a, b = jnp.asarray(_spd(4)), jnp.asarray(RNG.normal(size=(5, 4)), jnp.float32)
    batched = jax.vmap(in_a_loop)
    written = jax.vmap(rewrite(in_a_loop, [small_linalg.SMALL_LINALG]))
    assert {"cholesky", "triangular_solve"} <= _primitives(jax.make_jaxpr(batched)(a, b))
    assert not {"cholesky", "triangular_solve"} & _primitives(jax.make_jaxpr(written)(a, b))
    np.testing.assert_allclose(written(a, b), batched(a, b), rtol=1e-4, atol=1e-5)


def test_large_matrices_keep_the_library_calls():
    n = small_linalg.MAX_SIZE + 1
    written = rewrite(jnp.linalg.cholesky, [small_linalg.SMALL_LINALG])
    with pytest.warns(RuntimeWarning, match="'small_linalg' found nothing to rewrite"):
        jaxpr = jax.make_jaxpr(written)(jnp.asarray(_spd(n)[0]))
    assert "cholesky" in _primitives(jaxpr)


def _physics_step(env, write_out_linalg):
    return jax.vmap(functools.partial(physics.step_frames, env.mjx_model, n_frames=1,
                                      write_out_linalg=write_out_linalg))


def test_physics_step_written_out_matches_library():
    """halfcheetah (nv 9): the same physics step, to float32 rounding, without the library."""
    env = make_env("halfcheetah")
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 3))
    data = state.pipeline_state.replace(ctrl=jnp.full((3, env.action_size), 0.5))
    written = _physics_step(env, True)
    assert not {"cholesky", "triangular_solve"} & _primitives(jax.make_jaxpr(written)(data))
    library, written_out = jax.jit(_physics_step(env, False))(data), jax.jit(written)(data)
    for field in ("qpos", "qvel", "qacc"):
        np.testing.assert_allclose(getattr(written_out, field), getattr(library, field),
                                   rtol=1e-4, atol=1e-3)


def test_ant_keeps_the_library_calls():
    """ant's nv = 14 is above MAX_SIZE: by default nothing is written out on any device;
    asked for, the rewrite finds nothing to write out and says so."""
    env = make_env("ant")
    data = jax.vmap(lambda _: mjx.make_data(env.mjx_model))(jnp.arange(2))
    assert env.mjx_model.nv > small_linalg.MAX_SIZE
    assert "cholesky" in _primitives(jax.make_jaxpr(_physics_step(env, None))(data))
    with pytest.warns(RuntimeWarning, match="'small_linalg' found nothing to rewrite"):
        assert "cholesky" in _primitives(jax.make_jaxpr(_physics_step(env, True))(data))


def test_the_default_writes_out_on_a_gpu_and_keeps_the_library_calls_on_a_cpu():
    env = make_env("hopper")
    data = mjx.make_data(env.mjx_model)
    step = functools.partial(physics.step_frames, env.mjx_model, n_frames=1)
    library_calls = "cholesky" in _primitives(jax.make_jaxpr(step)(data))
    assert library_calls == (jax.default_backend() != "gpu")
    with jax.default_device(jax.devices("cpu")[0]):  # a GPU machine's CPU: the CPU's default
        assert "cholesky" in _primitives(jax.make_jaxpr(step)(data))

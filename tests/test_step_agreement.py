"""The measuring parts of `benchmarks.step_agreement`: TF32 rounding, its emulation in matrix
products only, and the relative difference of next observations."""

import dataclasses
import inspect

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import step_agreement


def test_tf32_rounds_to_the_nearest_value_of_ten_mantissa_bits():
    x = np.asarray(jax.random.normal(jax.random.PRNGKey(0), (1000,)) * 1e3, np.float32)
    rounded = np.asarray(step_agreement._tf32(jnp.asarray(x)))
    assert not np.any(rounded.view(np.uint32) & 0x1FFF)       # 13 low mantissa bits cleared
    spacing = np.abs(x) * 2.0 ** -10
    assert np.all(np.abs(rounded - x) <= 0.5 * spacing * (1 + 2.0 ** -10))
    assert np.mean(rounded != x) > 0.99


def test_tf32_products_round_matrix_products_alone_and_only_while_open():
    a, b = (jax.random.normal(jax.random.PRNGKey(k), (8, 8)) for k in (1, 2))
    v = jax.random.normal(jax.random.PRNGKey(3), (8,))
    tf32 = lambda m: np.asarray(step_agreement._tf32(m), np.float64)
    with step_agreement.tf32_products():
        inside = jax.jit(lambda a, b, v: (a @ b, a @ v))(a, b, v)
    outside = jax.jit(lambda a, b, v: (a @ b, a @ v))(a, b, v)
    np.testing.assert_allclose(inside[0], tf32(a) @ tf32(b), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(inside[1], outside[1])          # matrix-vector: float32
    exact = np.asarray(a, np.float64) @ np.asarray(b, np.float64)
    np.testing.assert_allclose(outside[0], exact, rtol=1e-5, atol=1e-5)
    assert np.abs(np.asarray(inside[0]) - exact).max() > 1e-3   # the rounding shows


@dataclasses.dataclass
class _State:
    obs: jax.Array


def test_differences_are_relative_to_each_envs_largest_observation():
    """A variant off by 0.01 in one component: 0.01 over each env's largest |observation|,
    along the reference's own rollout."""
    step = lambda s, a: _State(s.obs * 2.0 + a[:, :1])
    shifted = lambda s, a: _State(step(s, a).obs.at[:, 0].add(0.01))
    start = _State(jnp.array([[1.0, -4.0], [0.5, 0.25]]))
    got = step_agreement.differences(step, shifted, start, jax.random.PRNGKey(0),
                                     action_size=1, steps=3)
    state, expected = start, []
    for t in range(3):
        actions = jax.random.uniform(jax.random.fold_in(jax.random.PRNGKey(0), 1000 + t),
                                     (2, 1), minval=-1.0, maxval=1.0)
        state = step(state, actions)
        expected.append(0.01 / np.abs(np.asarray(state.obs)).max(axis=-1))
    np.testing.assert_allclose(got, np.stack(expected), rtol=1e-4)
    assert not step_agreement.differences(step, step, start, jax.random.PRNGKey(0), 1).any()


def test_tf32_products_within_a_module_round_its_products_alone():
    """Limited to the module that defines `jnp.dot`, its products are rounded; `lax.dot`'s,
    called from elsewhere, are not."""
    a, b = (jax.random.normal(jax.random.PRNGKey(k), (8, 8)) for k in (1, 2))
    tf32 = lambda m: np.asarray(step_agreement._tf32(m), np.float64)
    defining_module = inspect.unwrap(jnp.dot).__globals__["__name__"]
    with step_agreement.tf32_products(within=defining_module):
        inside, outside = jax.jit(lambda a, b: (jnp.dot(a, b), jax.lax.dot(a, b)))(a, b)
    np.testing.assert_allclose(inside, tf32(a) @ tf32(b), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(outside, np.asarray(a, np.float64) @ np.asarray(b, np.float64),
                               rtol=1e-5, atol=1e-5)
    assert np.abs(np.asarray(inside) - np.asarray(outside)).max() > 1e-3

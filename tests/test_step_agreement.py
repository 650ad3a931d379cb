"""The measuring parts of `benchmarks.step_agreement`: TF32 rounding, its emulation in matrix
products only, and the relative difference of next observations."""

import dataclasses
import types

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
    special = jnp.array([jnp.inf, -jnp.inf, jnp.nan], jnp.float32)
    np.testing.assert_array_equal(step_agreement._tf32(special), special)


def _tf32_f64(m):
    return np.asarray(step_agreement._tf32(m), np.float64)


def test_tf32_products_round_matrix_products_alone_and_only_while_open():
    """Matrix-matrix products are rounded inside the context, also those of a function
    traced before it; matrix-vector products and those asking for HIGHEST are not; outside,
    none is."""
    a, b = (jax.random.normal(jax.random.PRNGKey(k), (8, 8)) for k in (1, 2))
    v = jax.random.normal(jax.random.PRNGKey(3), (8,))
    products = jax.jit(lambda a, b, v: (a @ b, a @ v))
    products(a, b, v)   # traced and compiled before the context
    highest = lambda a, b: jnp.dot(a, b, precision=jax.lax.Precision.HIGHEST)
    with step_agreement.tf32_products():
        inside = products(a, b, v)
        np.testing.assert_allclose(jax.jit(highest)(a, b), np.asarray(a, np.float64)
                                   @ np.asarray(b, np.float64), rtol=1e-5, atol=1e-5)
    outside = products(a, b, v)
    np.testing.assert_allclose(inside[0], _tf32_f64(a) @ _tf32_f64(b), rtol=1e-5, atol=1e-5)
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


def test_tf32_products_within_a_module_round_the_products_it_calls_through_jnp():
    """Limited to a module, a product traced inside one of its functions, through `jnp`'s
    functions in between, is rounded; one traced here is not."""
    module = types.ModuleType("made_up_physics")
    exec("def product(a, b):\n    return a @ b\n", module.__dict__)
    a, b = (jax.random.normal(jax.random.PRNGKey(k), (6, 6)) for k in (1, 2))
    c, d = (jax.random.normal(jax.random.PRNGKey(k), (7, 7)) for k in (3, 4))  # own shapes
    with step_agreement.tf32_products(within="made_up_physics"):
        inside = jax.jit(module.product)(a, b)
        here = jax.jit(lambda c, d: c @ d)(c, d)
    np.testing.assert_allclose(inside, _tf32_f64(a) @ _tf32_f64(b), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(here, np.asarray(c, np.float64) @ np.asarray(d, np.float64),
                               rtol=1e-5, atol=1e-5)
    assert np.abs(np.asarray(inside) - np.asarray(a, np.float64) @ np.asarray(b, np.float64)
                  ).max() > 1e-3

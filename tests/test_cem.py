"""Diagonal CEM against a numpy transcription of its update (module docstring of cem)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pgps_jax.agent import cem


def numpy_tell(mean, damping, population, fitness, k, sigma_limit, tau_sigma, divide_by_k):
    order = np.argsort(-fitness)                     # maximise the return
    weights = np.array([np.log(1 + k) - np.log(i) for i in range(1, k + 1)])
    weights /= weights.sum()
    parents = population[order[:k]]
    new_mean = (weights[:, None] * parents).sum(0)
    spread = (weights[:, None] * (parents - mean) ** 2).sum(0)
    if divide_by_k:
        spread /= k
    new_var = spread + damping
    new_damping = (1 - tau_sigma) * damping + tau_sigma * sigma_limit
    return new_mean, new_var, new_damping, population[order[0]]


@pytest.mark.parametrize("divide_by_k", [True, False])
def test_tell_matches_numpy(divide_by_k):
    rng = np.random.default_rng(0)
    n, k, dim = 8, 4, 5
    mean = rng.normal(size=dim).astype(np.float32)
    population = rng.normal(size=(n, dim)).astype(np.float32)
    fitness = rng.normal(size=n).astype(np.float32)
    state = cem.CEMState(mean=jnp.asarray(mean), var=jnp.full(dim, 0.3),
                         damping=jnp.asarray(0.01), elite=jnp.zeros(dim))
    new = cem.tell(state, jnp.asarray(population), jnp.asarray(fitness), top_k=k,
                   sigma_limit=1e-5, sigma_decay=0.03, divide_by_k=divide_by_k)
    ref_mean, ref_var, ref_damp, ref_elite = numpy_tell(mean, 0.01, population, fitness, k,
                                                        1e-5, 0.03, divide_by_k)
    np.testing.assert_allclose(new.mean, ref_mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(new.var, ref_var, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(new.damping, ref_damp, rtol=1e-6)
    np.testing.assert_array_equal(new.elite, ref_elite)


def test_rank_weights_decrease_and_sum_to_one():
    w = np.asarray(cem.rank_weights(5))
    assert np.isclose(w.sum(), 1.0)
    assert np.all(np.diff(w) < 0)


def test_fitness_is_maximised():
    # The member with the highest return becomes the elite and pulls the mean toward it.
    population = jnp.array([[0.0], [10.0], [-10.0]])
    state = cem.init(jnp.zeros(1), 1e-2)
    new = cem.tell(state, population, jnp.array([0.0, 5.0, -5.0]), top_k=1, sigma_limit=1e-5,
                   sigma_decay=0.1, divide_by_k=True)
    assert float(new.elite[0]) == 10.0
    assert float(new.mean[0]) == 10.0


def test_damping_decays_toward_limit():
    state = cem.init(jnp.zeros(3), 7.5e-3)
    population, fitness = jnp.zeros((4, 3)), jnp.arange(4.0)
    for _ in range(500):
        state = cem.tell(state, population, fitness, top_k=2, sigma_limit=1e-5,
                         sigma_decay=0.03, divide_by_k=True)
    assert abs(float(state.damping) - 1e-5) < 1e-7
    np.testing.assert_allclose(state.var, 1e-5, rtol=1e-2)


def test_init_centres_on_mean_and_ask_samples_its_gaussian():
    mean = jnp.array([1.0, -2.0, 0.5])
    state = cem.init(mean, 0.25)
    np.testing.assert_array_equal(state.elite, mean)
    samples = np.asarray(cem.ask(jax.random.PRNGKey(0), state, 20_000))
    assert samples.shape == (20_000, 3)
    np.testing.assert_allclose(samples.mean(0), mean, atol=0.02)
    np.testing.assert_allclose(samples.std(0), 0.5, rtol=0.03)

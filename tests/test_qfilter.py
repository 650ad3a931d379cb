"""Q-critic filtering keeps exactly the candidates with the highest critic potential."""

import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax.agent import qfilter


def linear_actor(flat, obs):
    """A 'policy' whose action is its single parameter, whatever the state."""
    return jnp.broadcast_to(flat[:1], obs.shape[:-1] + (1,))


def q1(critic, obs, action):
    """Q1(s, a) = −(a − critic)² + s: peaks where the action equals the critic's target."""
    return -jnp.square(action[..., 0] - critic) + obs[..., 0]


def test_potentials_match_loop_over_candidates():
    candidates = jnp.linspace(-1, 1, 7)[:, None]
    states = jax.random.normal(jax.random.PRNGKey(0), (5, 1))
    scores = qfilter.potentials(linear_actor, q1, candidates, jnp.asarray(0.3), states)
    for j in range(7):
        expected = np.mean(q1(0.3, states, linear_actor(candidates[j], states)))
        np.testing.assert_allclose(scores[j], expected, rtol=1e-6)


def test_planted_best_candidates_are_kept():
    rng = np.random.default_rng(0)
    candidates = rng.uniform(2.0, 3.0, size=(50, 1)).astype(np.float32)
    planted = {17: 0.30, 4: 0.35, 41: 0.20}                  # closest to the critic's peak 0.3
    for index, value in planted.items():
        candidates[index] = value
    states = jnp.zeros((8, 1))
    scores = qfilter.potentials(linear_actor, q1, jnp.asarray(candidates), jnp.asarray(0.3), states)
    chosen = qfilter.select_best(jnp.asarray(candidates), scores, 3)
    np.testing.assert_allclose(np.asarray(chosen)[:, 0], [0.30, 0.35, 0.20])  # best first


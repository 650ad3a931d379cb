"""Replay buffer: masked insertion of variable-length episodes, wrap-around, sampling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pgps_jax.agent import buffer as replay


def rows(values, obs_size=2):
    """Transitions whose every field encodes `values` (shape = values.shape)."""
    v = jnp.asarray(values, jnp.float32)
    return replay.Transition(obs=jnp.repeat(v[..., None], obs_size, -1), action=v[..., None],
                             reward=v, next_obs=jnp.repeat(v[..., None] + 0.5, obs_size, -1),
                             discount=jnp.ones_like(v))


def test_variable_length_episodes_store_only_real_steps():
    # Three episodes padded to 4 steps ([time, episode] layout), lengths 4, 1 and 2.
    values = np.arange(12).reshape(4, 3) + 1
    valid = np.array([[1, 1, 1], [1, 0, 1], [1, 0, 0], [1, 0, 0]], bool)
    state = replay.add(replay.init(16, 2, 1), rows(values), jnp.asarray(valid))
    expected = values.reshape(-1)[valid.reshape(-1)]           # row-major order, real steps
    assert int(state.size) == valid.sum() == int(state.position)
    np.testing.assert_array_equal(state.data.reward[:valid.sum()], expected)
    np.testing.assert_array_equal(state.data.reward[valid.sum():], 0)
    np.testing.assert_array_equal(state.data.obs[:valid.sum(), 1], expected)


def test_wrap_around_overwrites_oldest_rows():
    state = replay.init(5, 2, 1)
    state = replay.add(state, rows([1, 2, 3, 4]), jnp.array([1, 1, 1, 0], bool))   # 1,2,3
    state = replay.add(state, rows([5, 6, 7, 8]), jnp.array([1, 0, 1, 1], bool))   # 5,7,8
    # ring of 5: 1,2,3,5,7 then 8 overwrites the oldest (row 0)
    np.testing.assert_array_equal(state.data.reward, [8, 2, 3, 5, 7])
    assert int(state.position) == 1 and int(state.size) == 5


def test_sampling_only_reads_filled_rows():
    state = replay.add(replay.init(100, 2, 1), rows(np.arange(1, 8)), jnp.ones(7, bool))
    batch = replay.sample(state, jax.random.PRNGKey(0), 500)
    assert set(np.unique(batch.reward)) == set(range(1, 8))
    np.testing.assert_array_equal(batch.obs[:, 0], batch.reward)           # rows stay intact
    states = replay.sample_obs(state, jax.random.PRNGKey(1), 300)
    assert states.shape == (300, 2) and set(np.unique(states[:, 0])) <= set(range(1, 8))


def test_invalid_capacity_is_refused():
    with pytest.raises(ValueError, match="capacity"):
        replay.init(0, 2, 1)

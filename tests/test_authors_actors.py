"""`benchmarks.authors_actors`: an actor vector in the authors' PyTorch layout played on our
envs, stepped by MJX and by MuJoCo's C engine."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import authors_actors
from pgps_jax.envs import make_env

OBS, HIDDEN, ACT = 8, authors_actors.HIDDEN, 2  # swimmer: no contacts, no constraint solve


def _write_actor(directory, seed: int = 0) -> np.ndarray:
    sizes = (OBS, *HIDDEN, ACT)
    count = sum(o * (i + 1) for i, o in zip(sizes[:-1], sizes[1:]))
    flat = np.random.default_rng(seed).normal(0, 1.0, count).astype(np.float32)
    np.save(directory / "Swimmer-v2.npy", flat)
    return flat


def test_an_actor_vector_is_read_in_pytorch_s_layout(tmp_path):
    flat = _write_actor(tmp_path)
    layers = authors_actors.load_actor(tmp_path / "Swimmer-v2.npy", OBS, ACT)["layers"]
    w1, b1 = layers[0]
    assert w1.shape == (HIDDEN[0], OBS) and b1.shape == (HIDDEN[0],)
    np.testing.assert_array_equal(np.asarray(w1).ravel(), flat[:HIDDEN[0] * OBS])
    np.testing.assert_array_equal(np.asarray(b1), flat[HIDDEN[0] * OBS:HIDDEN[0] * (OBS + 1)])
    assert [w.shape for w, _ in layers] == [(400, 8), (300, 400), (2, 300)]
    with pytest.raises(ValueError, match="do not make"):
        authors_actors.load_actor(tmp_path / "Swimmer-v2.npy", OBS + 500, ACT)


def test_the_c_engine_plays_the_episodes_that_mjx_plays(tmp_path):
    """On the swimmer (Euler, nothing for the solver to do) both engines integrate the same
    equations: over 100 steps (before a bang-bang actor's float32 and float64 runs part) the
    returns from the same start states agree."""
    _write_actor(tmp_path)
    mjx_run = authors_actors.play("swimmer", tmp_path, 2, {}, "mjx", steps=100)
    c_run = authors_actors.play("swimmer", tmp_path, 2, {}, "c", steps=100)
    assert mjx_run["lengths"] == c_run["lengths"] == [100, 100]
    assert abs(mjx_run["returns"][0] - mjx_run["returns"][1]) > 0.5  # two start states
    np.testing.assert_allclose(c_run["returns"], mjx_run["returns"], rtol=0.01, atol=0.05)


def test_a_c_engine_episode_whose_physics_fails_ends_without_that_step_s_reward(monkeypatch):
    """From a state too fast to step (MuJoCo resets it and warns), the episode ends at its
    first step with no reward, as MJX's guard ends it."""
    env = make_env("hopper")
    params = {"layers": [(jnp.zeros((3, env.observation_size)), jnp.zeros(3))]}
    reset = env.reset

    def exploding(key):
        state = reset(key)
        return state.replace(pipeline_state=state.pipeline_state.replace(
            qvel=jnp.full_like(state.pipeline_state.qvel, 1e11)))
    monkeypatch.setattr(env, "reset", exploding)
    assert authors_actors.c_episodes(env, params)(jax.random.PRNGKey(0), 10) == (0.0, 1)
    monkeypatch.setattr(env, "reset", reset)
    total, length = authors_actors.c_episodes(env, params)(jax.random.PRNGKey(0), 10)
    assert length == 10 and total > 0  # standing still: the healthy reward, every step

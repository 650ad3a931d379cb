"""Tests for MJX's Warp implementation as a task's physics (`Physics.impl="warp"`).

Warp's solver is MuJoCo's, not MJX's JAX one: with a truncated solve the two differ, but both
solved to convergence must play the same episodes, which checks that the model, its solver
settings, the frame skip and the reset reach Warp as they reach JAX.
"""

import dataclasses

import jax
import jax.numpy as jnp
from mujoco import mjx
import numpy as np
import pytest

from pgps_jax.cli.assignments import env_assignments
from pgps_jax.envs import env_batches, make_env
from pgps_jax.experiments.paper import command

from conftest import REDUCED_CELL

N_ENVS = 3
CONVERGED = dict(iterations=50, ls_iterations=50)


def _episodes(env, n_steps: int):
    """Observations, rewards and dones of `n_steps` random actions from a batched reset."""
    key_reset, key_actions = jax.random.split(jax.random.PRNGKey(0))
    actions = jax.random.uniform(key_actions, (n_steps, N_ENVS, env.action_size),
                                 minval=-1.0, maxval=1.0)

    @jax.jit
    def play(keys, actions):
        def step(state, action):
            state = jax.vmap(env.step)(state, action)
            return state, (state.obs, state.reward, state.done)
        return jax.lax.scan(step, jax.vmap(env.reset)(keys), actions)[1]

    return jax.tree.map(np.asarray, play(jax.random.split(key_reset, N_ENVS), actions))


@pytest.mark.parametrize("task, n_steps", [("hopper", 20), ("ant", 8)])
def test_warp_plays_jax_episodes_when_both_converge(task, n_steps):
    """Hopper (Euler) and the ant (RK4, every geom on Gym's floor contacts): the same
    episodes to float tolerance."""
    warp_env = make_env(task, impl="warp", **CONVERGED)
    assert warp_env.mjx_model.impl == mjx.Impl.WARP and warp_env.reset(
        jax.random.PRNGKey(0)).pipeline_state.impl == mjx.Impl.WARP
    on_jax = _episodes(make_env(task, **CONVERGED), n_steps)
    on_warp = _episodes(warp_env, n_steps)
    for name, a, b in zip(("obs", "reward", "done"), on_jax, on_warp):
        np.testing.assert_allclose(b, a, atol=1e-3, rtol=1e-4, err_msg=name)
    assert np.abs(on_jax[0][-1] - on_jax[0][0]).max() > 0.1  # the bodies did move


def test_nan_guard_keeps_a_warp_env_finite():
    """A NaN action ends its episode and keeps its previous physics; the other envs, whose
    contacts share Warp's arrays with it, step on."""
    env = make_env("hopper", impl="warp")
    assert env.mjx_model.impl == mjx.Impl.WARP
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    state = reset(jax.random.split(jax.random.PRNGKey(0), N_ENVS))
    action = jnp.full((N_ENVS, env.action_size), 0.5).at[1, 0].set(jnp.nan)
    after = step(state, action)
    np.testing.assert_array_equal(after.metrics["unstable"], [0.0, 1.0, 0.0])
    np.testing.assert_array_equal(after.pipeline_state.qpos[1], state.pipeline_state.qpos[1])
    assert not np.array_equal(after.pipeline_state.qpos[0], state.pipeline_state.qpos[0])
    again = step(after, jnp.zeros((N_ENVS, env.action_size)))
    assert np.isfinite(again.obs).all() and not again.metrics["unstable"].any()


def test_warp_and_jax_differ_with_a_truncated_solve():
    """With hopper's one solver iteration the two engines' episodes part: Warp is other
    physics, recorded as such."""
    on_jax = _episodes(make_env("hopper"), 5)
    on_warp = _episodes(make_env("hopper", impl="warp"), 5)
    assert np.abs(on_warp[0] - on_jax[0]).max() > 1e-2
    assert make_env("hopper", impl="warp").settings()["impl"] == "warp"


def test_unknown_impl_names_the_choices():
    with pytest.raises(ValueError, match="impl must be one of jax, warp, got 'cuda'"):
        make_env("hopper", impl="cuda")


def _rows(tree, rows):
    return jax.tree.map(lambda x: np.asarray(x)[rows], tree)


@pytest.mark.parametrize("impl", ["jax", "warp"])
def test_batches_join_slice_and_choose_env_by_env(impl):
    """A batch joined from two steps as the two batches step apart; its slices and a choice
    between two batches give each env's own state; Warp's arrays of the whole batch (its
    contacts) keep their size through all three."""
    env = make_env("hopper", impl=impl)
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    first = reset(jax.random.split(jax.random.PRNGKey(0), 2))
    second = step(reset(jax.random.split(jax.random.PRNGKey(1), 3)),
                  jnp.full((3, env.action_size), 0.3))
    joined = env_batches.concatenate(first, second)
    actions = jax.random.uniform(jax.random.PRNGKey(2), (5, env.action_size), minval=-1.0)
    stepped = step(joined, actions)
    for part, rows, alone in ((first, slice(0, 2), step(first, actions[:2])),
                              (second, slice(2, 5), step(second, actions[2:]))):
        np.testing.assert_allclose(_rows(stepped.obs, rows), alone.obs, rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(
            env_batches.rows(joined, rows.start, rows.stop).pipeline_state.qpos,
            part.pipeline_state.qpos)
    chosen = env_batches.select(jnp.array([True, False, False, True, False]), stepped, joined)
    for i, source in enumerate((stepped, joined, joined, stepped, joined)):
        np.testing.assert_array_equal(_rows(chosen.obs, i), _rows(source.obs, i))
        np.testing.assert_array_equal(_rows(chosen.pipeline_state.qvel, i),
                                      _rows(source.pipeline_state.qvel, i))
    if impl == "warp":
        for batch in (joined, chosen, env_batches.rows(joined, 1, 4)):
            assert batch.pipeline_state._impl.contact__pos.shape == (
                first.pipeline_state._impl.contact__pos.shape)


def test_a_cell_trains_on_warp(tmp_path):
    """The experiment runner's tiny hopper cell on Warp, saving checkpoints of Warp's env
    states on the way (the cell spent time writing them; they are removed once it is done): two
    seeds whose episodes end apart, so that they reach the budget in different generations
    (one waits for the other), with finite returns and Warp recorded as the cell's physics.
    A sixth of the reduced budget after a fifth of its warm-up (40 random steps, then two or
    three generations; the Q-filter, from 400 steps, does not start), with test episodes of
    20 steps: on a CPU each of Warp's env steps takes about 0.15 s."""
    overrides = dict(REDUCED_CELL.overrides, warmup_steps=40)
    budget = dataclasses.replace(REDUCED_CELL, steps=100, env=(("impl", "warp"),),
                                 overrides=tuple(overrides.items()),
                                 evaluation=dataclasses.replace(REDUCED_CELL.evaluation,
                                                                steps=20))
    (result,) = command.run("figure4", tmp_path, budget, tasks=["hopper"], configs=["pgps"],
                            progress=False)
    assert min(result["env_steps"]) >= budget.steps
    assert np.isfinite(result["final"]["mu"]).all()
    assert result["settings"]["physics"]["impl"] == "warp"
    assert result["wall_split_s"]["checkpoints"] > 0
    cell = tmp_path / "figure4" / "hopper" / "pgps"
    generations = [len((cell / f"seed{seed}_generations.csv").read_text().splitlines())
                   for seed in (1, 2)]
    if jax.default_backend() == "cpu":  # these seeds' CPU trajectories reach it apart
        assert generations[0] != generations[1]


def test_the_commands_take_warp():
    assert env_assignments(["impl=warp", "iterations=2"]) == {"impl": "warp", "iterations": 2}

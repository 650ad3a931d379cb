"""Table 1's time split (`benchmarks.time_split`): the generation timed is a late run's (full
episodes, the TD3 actor lagging), each part timed alone computes what the generation computed
in it, and a model's split has Table 1's columns."""

import dataclasses
import functools
import pathlib
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.time_split import (TABLE1_COLUMNS, FullEpisodes, lagging_generation,
                                   lagging_returns, model_split, parts_of, table1_time)
from benchmarks.timing import results_path
from pgps_jax.agent.config import EvaluationConfig, PGPSConfig
from pgps_jax.agent.couplings import couplings_of
from pgps_jax.agent.pgps import PGPS, fell_behind
from pgps_jax.envs import make_env


pytestmark = pytest.mark.xdist_group("time_split")  # one worker compiles the programs once


@functools.lru_cache(maxsize=None)
def point_pgps(pop_size: int, **overrides) -> tuple[PGPS, object]:
    """A tiny PGPS on the point mass, Q-filtering from the start, and its initial state (made
    once per settings and worker; the state is never donated)."""
    config = PGPSConfig(pop_size=pop_size, top_k=pop_size // 2, actor_hidden=(8,),
                        critic_hidden=(8,), batch_size=8, buffer_size=500, warmup_steps=40,
                        t_init=10, t_max=10, q_filter_start=0, sample_ratio=2, ss1_size=4,
                        ss2_size=8, **overrides)
    agent = PGPS(config, make_env("point"), EvaluationConfig(every=100, episodes=1, steps=10))
    return agent, jax.jit(agent.init)(jax.random.PRNGKey(0), jax.random.PRNGKey(1))


@functools.lru_cache(maxsize=None)
def jitted_generation(agent: PGPS):
    """`lagging_generation` of `agent`, jitted (once per agent and worker)."""
    return jax.jit(lambda s: lagging_generation(agent, s))


@functools.lru_cache(maxsize=None)
def jitted_parts(agent: PGPS) -> dict:
    """`parts_of(agent)`, each part's function jitted (once per agent and worker)."""
    return {name: (jax.jit(part), inputs) for name, (part, inputs) in parts_of(agent).items()}


def model_state(agent: PGPS, state, **couplings):
    """`state` switched to the model of `agent`'s configuration with `couplings` changed."""
    model = dataclasses.replace(agent.config, **couplings)
    return state.replace(couplings=couplings_of(agent.config, model))


def test_full_episodes_leave_the_task_as_it_is_but_never_end_it():
    hopper = make_env("hopper")
    start = hopper.reset(jax.random.PRNGKey(0))
    fallen = start.replace(pipeline_state=start.pipeline_state.replace(
        qpos=start.pipeline_state.qpos.at[1].set(-1.0)))  # the torso far below its range
    action = jnp.full((hopper.action_size,), 0.3)
    raw = jax.jit(hopper.step)(fallen, action)
    full = jax.jit(FullEpisodes(hopper).step)(fallen, action)
    assert raw.done == 1.0 and full.done == 0.0
    assert jnp.array_equal(raw.obs, full.obs) and raw.reward == full.reward


def test_the_lagging_generation_trains_on_the_augmented_loss_only_where_ea_guides_pg():
    agent, state = point_pgps(pop_size=4)
    generation = jitted_generation(agent)
    for ea_guides_pg in (False, True):
        _, metrics, played = generation(model_state(agent, state, ea_guides_pg=ea_guides_pg))
        assert bool(metrics["td3/guided_loss"]) == ea_guides_pg
        returns = [metrics[f"pop/return_{i}"] for i in range(agent.config.pop_size)]
        assert returns[-1] < min(returns[:-1])  # the TD3 actor's slot, lowest
        np.testing.assert_array_equal(played.episodes.returns[:agent.config.pop_size], returns)


def test_lagging_returns_fall_behind_however_the_others_spread():
    key = jax.random.PRNGKey(0)
    for n in (3, 4, 6, 10):
        for spread in (1e-3, 1.0, 1e4):
            key, draw = jax.random.split(key)
            returns = spread * jax.random.normal(draw, (n,))
            for outlier in (0.0, 100 * spread):  # one far above the rest widens the std
                hostile = returns.at[0].add(outlier)
                lagging = lagging_returns(hostile, n - 1)
                assert jnp.array_equal(lagging[:-1], hostile[:-1])
                assert fell_behind(lagging[-1], lagging, "mean_minus_std")
                assert fell_behind(lagging[-1], lagging, "mean")


@pytest.mark.parametrize("couplings,overrides", [
    (dict(), dict()),
    (dict(pg_guides_ea=False, ea_guides_pg=False, q_filter=False), dict()),
    (dict(), dict(target_actor_from_elite=True))])
def test_each_part_alone_computes_what_the_generation_computed_in_it(couplings, overrides):
    """The full model (Q-filtered, the TD3 actor injected and guided), the Base model, and the
    full model with the TD3 target actor reset to the elite before the updates."""
    agent, state = point_pgps(pop_size=4, **overrides)
    state = model_state(agent, state, **couplings)
    after, metrics, played = jitted_generation(agent)(state)
    guided = metrics["td3/guided_loss"]
    parts = {name: part(*inputs(state, played, after, guided))
             for name, (part, inputs) in jitted_parts(agent).items()}
    # compiled alone, the sampling may round apart from the generation's (XLA fuses it otherwise)
    np.testing.assert_allclose(parts["population_generation"], played.population, rtol=1e-6)
    jax.tree.map(np.testing.assert_array_equal, parts["cem_update"], after.cem)
    buffer, td3, beta, _ = parts["td3_update"]  # compiled alone: equal to float tolerance
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6),
                 (buffer, td3, beta), (after.buffer, after.td3, after.beta))


def test_a_model_s_split_has_table1_s_columns_and_says_whether_it_trained_on_l_a():
    agent, state = point_pgps(pop_size=4)
    split = model_split(jitted_generation(agent), jitted_parts(agent), state, repeats=2)
    ms = split["ms_per_generation"]
    assert set(ms) == {phase for phase, _ in TABLE1_COLUMNS}
    assert split["guided"] is True  # the full model's TD3 actor, lagging, trained on L^A
    runs = split["generation_ms_runs"]  # each timed run kept; the split is of their median
    assert len(runs) == 2 and min(runs) > 0 and split["total_ms"] == np.median(runs)
    assert sum(ms.values()) == pytest.approx(split["total_ms"])


def test_table1_s_time_averages_each_model_s_normalised_phases_over_the_tasks():
    phases = [phase for phase, _ in TABLE1_COLUMNS]
    shares = np.random.default_rng(0).uniform(0, 1, (2, 3, len(phases)))  # task, model, phase
    tasks = [{"task": task, "models": [{"model": model, "normalised": dict(zip(phases, row))}
                                       for model, row in zip(("base", "q_filter", "pgps"), rows)]}
             for task, rows in zip(("halfcheetah", "ant"), shares)]
    lines = table1_time(tasks).splitlines()
    assert len(lines) >= 6  # header, rule, the three models' rows, a blank, the tasks
    expected = shares.mean(axis=0)  # the paper's average over its games
    for model, row, line in zip(("base", "q_filter", "pgps"), expected, lines[2:5]):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[0] == model
        np.testing.assert_allclose([float(c) for c in cells[1:]], [row.sum(), *row], atol=5e-4)
    assert "halfcheetah, ant" in lines[-1]


def test_a_smoke_check_never_writes_over_a_committed_result():
    default = "benchmarks/results/time_split.json"
    assert results_path(None, default, smoke=False) == pathlib.Path(default)
    smoke = results_path(None, default, smoke=True)
    assert smoke.name == "time_split.json"
    assert smoke.is_relative_to(tempfile.gettempdir())
    assert results_path("runs/split.json", default, smoke=True) == pathlib.Path("runs/split.json")

"""Table 1's time split (`benchmarks.time_split`): the generation program's operations carry
the four phases of the paper as named scopes, a profile's device time is attributed to them,
and the generation timed is a late run's (full episodes, the TD3 actor lagging)."""

import dataclasses
import glob
import os

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import physics_profile
from benchmarks.time_split import (TABLE1_COLUMNS, FullEpisodes, counted_events,
                                   lagging_generation, lagging_returns, phases_of, split,
                                   table1_time)
from pgps_jax.agent.config import EvaluationConfig, PGPSConfig
from pgps_jax.agent.couplings import couplings_of
from pgps_jax.agent.pgps import PGPS, PHASES, fell_behind
from pgps_jax.envs import make_env


def point_pgps(pop_size: int) -> tuple[PGPS, object]:
    """A tiny PGPS on the point mass, Q-filtering from the start, and its initial state."""
    config = PGPSConfig(pop_size=pop_size, top_k=pop_size // 2, actor_hidden=(8,),
                        critic_hidden=(8,), batch_size=8, buffer_size=500, warmup_steps=40,
                        t_init=10, t_max=10, q_filter_start=0, sample_ratio=2, ss1_size=4,
                        ss2_size=8)
    agent = PGPS(config, make_env("point"), EvaluationConfig(every=100, episodes=1, steps=10))
    return agent, jax.jit(agent.init)(jax.random.PRNGKey(0), jax.random.PRNGKey(1))


def test_the_generation_program_carries_every_phase_of_table1():
    agent, state = point_pgps(pop_size=2)
    text = jax.jit(agent.generation_step).lower(state).compile().as_text()
    assert set(PHASES) <= set(phases_of(text).values())


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
    config = agent.config
    generation = jax.jit(lambda s: lagging_generation(agent, s))
    for ea_guides_pg in (False, True):
        model = dataclasses.replace(config, ea_guides_pg=ea_guides_pg)
        switched = state.replace(couplings=couplings_of(config, model))
        _, metrics = generation(switched)
        assert bool(metrics["td3/guided_loss"]) == ea_guides_pg
        returns = [metrics[f"pop/return_{i}"] for i in range(config.pop_size)]
        assert returns[-1] < min(returns[:-1])  # the TD3 actor's slot, lowest
    text = generation.lower(switched).compile().as_text()  # the program timed
    assert set(PHASES) <= set(phases_of(text).values())


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


def test_a_profile_s_time_goes_to_the_scopes_of_its_operations_once(tmp_path):
    def work(x):
        with jax.named_scope("td3_update"):
            y = jax.lax.fori_loop(0, 3, lambda i, y: jnp.tanh(y @ x), x)
        with jax.named_scope("cem_update"):
            z = jax.lax.cond(y[0, 0] > 0, lambda y: jnp.sin(y @ y), jnp.cos, y)
            return z.sum(0)

    x = jax.device_put(jnp.ones((128, 128)) / 128, jax.devices("cpu")[0])  # the CPU's trace
    compiled = jax.jit(work).lower(x).compile()
    jax.block_until_ready(compiled(x))
    with jax.profiler.trace(str(tmp_path), create_perfetto_trace=True):
        for _ in range(3):
            jax.block_until_ready(compiled(x))
    trace, = glob.glob(os.path.join(tmp_path, "**", "perfetto_trace.json.gz"), recursive=True)
    phases = phases_of(compiled.as_text())
    assert None in phases.values()  # the loop and the conditional: their operations count
    ms, _ = split(trace, phases, 3, "cpu")
    assert ms["td3_update"] > 0 and ms["cem_update"] > 0
    assert ms["population_generation"] == ms["actors_evaluation"] == 0
    spans = sorted((e["tid"], e["ts"], e["ts"] + e["dur"])
                   for e, _, _ in counted_events(trace, phases, "cpu"))
    for (tid, _, end), (next_tid, start, _) in zip(spans, spans[1:]):
        assert tid != next_tid or start >= end  # none counted inside another


def test_nested_scopes_count_for_the_innermost():
    def work(x):
        with jax.named_scope("outer"):
            y = jnp.exp(x)
            with jax.named_scope("inner"):
                return jnp.sin(y) * 2.0

    text = jax.jit(work).lower(jnp.ones(3)).compile().as_text()
    assert {"outer", "inner"} <= set(phases_of(text, ("outer", "inner")).values())
    assert "inner" not in phases_of(text, ("outer",)).values()


def test_the_physics_profile_names_each_stage_of_a_mujoco_step():
    """`benchmarks.physics_profile` on hopper (contacts, Newton solver): every stage it scopes
    runs kernels, and together they run most of the env step's (the rest: the env's own
    observation, reward and guard, and the loops' bookkeeping); MJX's own functions are left
    as they were."""
    originals = {name: getattr(module, name)
                 for name, module in physics_profile.SCOPED_HERE.items()}
    profile = physics_profile.profile_task("hopper", batch=2, steps=2, calls=1)
    stages = profile["stages"]
    for stage in ("kinematics", "crb", "collision", "make_constraint", "fwd_velocity", "solve",
                  "euler"):
        assert stages[stage]["kernels"] > 0 and stages[stage]["device_ms"] > 0, stage
    unscoped = stages.get("other", {"kernels": 0})["kernels"]
    assert unscoped < 0.4 * profile["kernels_per_env_step"]  # the stages hold most of it
    assert {name: getattr(module, name)
            for name, module in physics_profile.SCOPED_HERE.items()} == originals


def test_table1_s_time_averages_each_model_s_normalised_phases_over_the_tasks():
    phases = [phase for phase, _ in TABLE1_COLUMNS]
    shares = np.random.default_rng(0).uniform(0, 1, (2, 3, len(phases)))  # task, model, phase
    tasks = [{"task": task, "models": [{"model": model, "normalised": dict(zip(phases, row))}
                                       for model, row in zip(("base", "q_filter", "pgps"), rows)]}
             for task, rows in zip(("halfcheetah", "ant"), shares)]
    lines = table1_time(tasks).splitlines()
    expected = shares.mean(axis=0)  # the paper's average over its games
    for model, row, line in zip(("base", "q_filter", "pgps"), expected, lines[2:5]):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[0] == model
        np.testing.assert_allclose([float(c) for c in cells[1:]], [row.sum(), *row], atol=5e-4)
    assert "halfcheetah, ant" in lines[-1]


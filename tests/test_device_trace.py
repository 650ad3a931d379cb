"""Device time per named scope (`benchmarks.device_trace`): a program's operations carry their
scopes, a profile's device time goes to them once each, and the physics profile built on it
names the stages of a MuJoCo step."""

import collections
import glob
import os

import jax
import jax.numpy as jnp

from benchmarks import physics_profile
from benchmarks.device_trace import counted_events, phases_of
from pgps_jax.agent.config import EvaluationConfig, PGPSConfig
from pgps_jax.agent.pgps import PGPS, PHASES
from pgps_jax.envs import make_env


def test_the_generation_program_carries_every_phase_of_table1():
    config = PGPSConfig(pop_size=2, top_k=1, actor_hidden=(8,), critic_hidden=(8,),
                        batch_size=8, buffer_size=500, warmup_steps=40, t_init=10, t_max=10,
                        q_filter_start=0, sample_ratio=2, ss1_size=4, ss2_size=8)
    agent = PGPS(config, make_env("point"), EvaluationConfig(every=100, episodes=1, steps=10))
    state = jax.jit(agent.init)(jax.random.PRNGKey(0), jax.random.PRNGKey(1))
    text = jax.jit(agent.generation_step).lower(state).compile().as_text()
    assert set(PHASES) <= set(phases_of(text, PHASES).values())


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
    phases = phases_of(compiled.as_text(), PHASES)
    assert None in phases.values()  # the loop and the conditional: their operations count
    events = counted_events(trace, phases, "cpu")
    device_us = collections.Counter()
    for event, _, phase in events:
        device_us[phase] += event["dur"]
    assert device_us["td3_update"] > 0 and device_us["cem_update"] > 0
    assert device_us["population_generation"] == device_us["actors_evaluation"] == 0
    spans = sorted((e["tid"], e["ts"], e["ts"] + e["dur"]) for e, _, _ in events)
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

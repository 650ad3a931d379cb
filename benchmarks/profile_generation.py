"""A device profile of one late-run PGPS generation: where its time goes and what waits.

halfcheetah, paper configuration, at 600k env steps (T = 1000, Q-filtering on) with a full
1M-row replay buffer of random transitions, a test evaluation under way. After compilation,
`generation_step` runs under `jax.profiler.trace`; the Perfetto trace is summarised into
`benchmarks/results/profile_generation.json`: wall time per generation, device kernel time,
device idle time, kernel and memory-copy counts by direction, and the kernels taking the most
time. Also timed at the same state, each jitted alone: the rollout, `td3.train` with the full
buffer and with a 10k-row buffer (does gathering from 1M rows cost more?).

    python -m benchmarks.profile_generation
"""

import argparse
import collections
import glob
import gzip
import json
import os
import sys
import tempfile
import time

import jax
import jax.numpy as jnp

from benchmarks.timing import results_path, timed
from pgps_jax.agent import buffer as replay
from pgps_jax.agent.config import EvaluationConfig, for_task
from pgps_jax.agent.pgps import PGPS, episode_limit
from pgps_jax.envs import make_env

SMOKE = "--smoke" in sys.argv
SMOKE_SIZES = dict(t_init=10, t_max=20, t_interval=1000, buffer_size=5000, warmup_steps=200,
                   q_filter_start=400, actor_hidden=(16, 16), critic_hidden=(16, 16),
                   sample_ratio=2)
"""The configuration's sizes at --smoke (a CPU check of a benchmark script): T = T_max and
Q-filtering on from 400 steps, so that `late_state`'s 2k steps are a late run's."""


def tests_of(smoke: bool) -> EvaluationConfig:
    """The test evaluation: the paper's, or of 20-step episodes at `smoke` sizes."""
    return EvaluationConfig(steps=20) if smoke else EvaluationConfig()


TESTS = tests_of(SMOKE)


def late_state(config, env, smoke: bool = SMOKE):
    """The state of a run at 600k env steps (2k at `smoke` sizes): full buffer of random
    rows, an evaluation (`tests_of`) due. Initialised without the random warm-up, whose
    buffer and step count it replaces (and whose rollout would compile the physics)."""
    cold = PGPS(config.replace(warmup_steps=0), env, tests_of(smoke))
    state = jax.jit(cold.init)(jax.random.PRNGKey(0))
    capacity = config.buffer_size
    k = jax.random.split(jax.random.PRNGKey(1), 5)
    data = replay.Transition(
        obs=jax.random.normal(k[0], (capacity, env.observation_size)),
        action=jax.random.uniform(k[1], (capacity, env.action_size), minval=-1, maxval=1),
        reward=jax.random.normal(k[2], (capacity,)),
        next_obs=jax.random.normal(k[3], (capacity, env.observation_size)),
        discount=jnp.ones((capacity,)))
    buffer = replay.BufferState(data=data, position=jnp.zeros((), jnp.int32),
                                size=jnp.asarray(capacity, jnp.int32))
    late = 600_000 if not smoke else 2_000
    return state.replace(buffer=buffer, total_steps=jnp.asarray(late, jnp.int32),
                         evaluation=state.evaluation.replace(
                             next_due=jnp.asarray(late, jnp.int32)))


def summarise(trace_file: str, generations: int) -> dict:
    """Kernel time, idle gaps and copies of the device in a Perfetto JSON trace."""
    with gzip.open(trace_file) as f:
        events = json.load(f)["traceEvents"]
    names = {e["pid"]: e["args"]["name"] for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    device_pids = {pid for pid, name in names.items() if "GPU" in name or "gpu" in name}
    spans = [e for e in events if e.get("ph") == "X" and e.get("pid") in device_pids]
    copies = collections.Counter()
    kernels = collections.defaultdict(lambda: [0, 0.0])
    for e in spans:
        lowered = e["name"].lower()
        if "memcpy" in lowered or "memset" in lowered:
            direction = next((d for d in ("htod", "dtoh", "dtod", "memset")
                              if d in lowered.replace("_", "").replace("2", "to")), "other")
            copies[direction] += 1
        else:
            kernels[e["name"]][0] += 1
            kernels[e["name"]][1] += e["dur"]
    intervals = sorted((e["ts"], e["ts"] + e["dur"]) for e in spans)
    busy, end, start = 0.0, None, intervals[0][0] if intervals else 0.0
    for a, b in intervals:
        if end is None or a > end:
            busy += b - a
            end = b
        elif b > end:
            busy += b - end
            end = b
    span = (end - start) if intervals else 0.0
    top = sorted(kernels.items(), key=lambda kv: -kv[1][1])[:25]
    host = collections.defaultdict(lambda: [0, 0.0])
    for e in events:
        if e.get("ph") == "X" and e.get("pid") not in device_pids:
            host[e["name"]][0] += 1
            host[e["name"]][1] += e.get("dur", 0.0)
    top_host = sorted(host.items(), key=lambda kv: -kv[1][1])[:25]
    return {
        "processes": sorted(set(names.values())),
        "device_processes": sorted(names[p] for p in device_pids),
        "device_events": len(spans),
        "kernels_per_generation": sum(v[0] for v in kernels.values()) / generations,
        "device_span_ms_per_generation": span / 1e3 / generations,
        "device_busy_ms_per_generation": busy / 1e3 / generations,
        "device_idle_fraction": 1 - busy / span if span else None,
        "copies_per_generation": {k: v / generations for k, v in copies.items()},
        "top_kernels": [{"name": name[:120], "count_per_generation": c / generations,
                         "ms_per_generation": t / 1e3 / generations} for name, (c, t) in top],
        "top_host_events": [{"name": name[:120], "count_per_generation": c / generations,
                             "ms_per_generation": t / 1e3 / generations}
                            for name, (c, t) in top_host],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", help="default: benchmarks/results/profile_generation.json; with "
                        "--smoke, the same name in a temporary directory")
    parser.add_argument("--generations", type=int, default=2)
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    args.out = results_path(args.out, "benchmarks/results/profile_generation.json", args.smoke)
    config = for_task("halfcheetah", **(SMOKE_SIZES if SMOKE else {}))
    env = make_env("halfcheetah")
    state = late_state(config, env)
    agent = PGPS(config, env, TESTS)
    step = jax.jit(agent.generation_step)
    first_s, generation_s = timed(step, state, repeats=3)

    td3, unflatten = agent.td3, agent.actor
    num_update = config.pop_size * config.t_max // config.update_blocks
    key = jax.random.PRNGKey(2)
    train = jax.jit(lambda s: td3.train(s.td3, s.buffer, key, jnp.asarray(num_update),
                                        num_update, unflatten(s.cem.elite),
                                        jnp.asarray(False), s.beta))
    _, train_full_s = timed(train, state, repeats=2)
    small = state.buffer.replace(size=jnp.asarray(10_000 if not SMOKE else 200, jnp.int32))
    _, train_small_s = timed(train, state.replace(buffer=small), repeats=2)

    with tempfile.TemporaryDirectory() as log_dir:
        with jax.profiler.trace(log_dir, create_perfetto_trace=True):
            start = time.perf_counter()
            for _ in range(args.generations):
                out = step(state)
            jax.block_until_ready(out)
            traced_s = (time.perf_counter() - start) / args.generations
        trace = glob.glob(os.path.join(log_dir, "**", "perfetto_trace.json.gz"), recursive=True)
        profile = summarise(trace[0], args.generations) if trace else {"trace": "not written"}

    result = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
              "generation_T": int(episode_limit(state.total_steps, config)),
              "generation_step_ms": generation_s * 1e3,
              "generation_step_compile_s": first_s - generation_s,
              "generation_step_ms_under_trace": traced_s * 1e3,
              "td3_train_ms": {"buffer_1M_rows": train_full_s * 1e3,
                               "buffer_10k_rows": train_small_s * 1e3,
                               "update_pairs": num_update * config.update_blocks},
              "profile": profile}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

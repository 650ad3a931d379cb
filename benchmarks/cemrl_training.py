"""CEM-RL's training of half its population: `CEMRL.train_half` against the same updates
run one actor after the other, the order of its authors' code (`es_grad.py`).

On each task, one late generation of the paper's CEM-RL configuration: S = N·T_max env steps
(10 × 1,000), so the critic's N/2 blocks of S/(N/2) updates, then S actor updates for each
of the N/2 actors. `train_half` runs the critic's blocks in sequence and the actors side by
side (N/2-fold fewer sequential updates); the reference runs each actor's block and its S
updates before the next actor's, in one `lax.scan`. Each is a jitted program of its own,
compiled and run once, then timed (median of `--repeats`). The entry also records how far
apart the two programs' trained actors end, against how far training moved them: the same
updates, but their matrix products are batched differently, so their rounding may differ,
and Adam carries such differences on from update to update.

    python -m benchmarks.cemrl_training --tasks halfcheetah ant
    python -m benchmarks.cemrl_training --tasks halfcheetah --t-max 10 100 300 1000
    python -m benchmarks.cemrl_training --smoke      # tiny sizes: a CPU check

Writes `benchmarks/results/cemrl_training.json`.
"""

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.timing import provenance, repeated_seconds, results_path
from pgps_jax.agent import buffer as replay
from pgps_jax.agent.algorithms import make_agent
from pgps_jax.agent.config import EvaluationConfig, for_task
from pgps_jax.agent.networks import flatten
from pgps_jax.agent.td3 import repeat
from pgps_jax.envs import make_env

SMOKE_SIZES = dict(t_max=20, t_init=20, buffer_size=2000, warmup_steps=500, batch_size=32,
                   actor_hidden=(16, 16), critic_hidden=(16, 16))


def one_after_the_other(agent, td3_state, buffer, key, actors, steps):
    """The trained actors [N/2, P] of `actors`, each trained in turn: the shared critic's
    block toward its target actions, then its S updates, before the next actor's block."""
    td3, c = agent.td3, agent.config
    critic_updates = steps // agent.num_trained

    def train_one(td3_state, inputs):
        flat, actor_key = inputs
        actor = agent.actor(flat)
        td3_state = td3_state.replace(actor=actor, actor_target=actor,
                                      actor_opt=td3.actor_optimizer.init(actor))
        batch_key, noise_key, obs_key = jax.random.split(actor_key, 3)

        def critic_step(j, td3_state):
            batch = replay.sample(buffer, jax.random.fold_in(batch_key, j), c.batch_size)
            noise = td3.smoothing_noise(jax.random.fold_in(noise_key, j),
                                        (c.batch_size, td3.action_size))
            next_action = td3.target_actions(td3_state.actor_target, batch.next_obs, noise)
            return td3.critic_update(td3_state, batch, next_action)[0]

        def actor_step(j, td3_state):
            obs = replay.sample_obs(buffer, jax.random.fold_in(obs_key, j), c.batch_size)
            return td3.actor_update(td3_state, obs, jnp.zeros((c.batch_size, td3.action_size)),
                                    jnp.zeros(()))[0]

        td3_state = repeat(critic_updates, critic_step, td3_state, c.update_unroll)
        td3_state = repeat(steps, actor_step, td3_state, c.update_unroll)
        return td3_state, flatten(td3_state.actor)

    return jax.lax.scan(train_one, td3_state,
                        (actors, jax.random.split(key, agent.num_trained)))[1]


def measure(task: str, repeats: int, sizes: dict) -> dict:
    """Both programs on `task` (the paper's configuration with `sizes` changed):
    compile-and-run seconds, the median of `repeats` runs, µs per sequential update, and
    how far apart their trained actors end."""
    config = for_task(task, "cemrl", **sizes)
    agent = make_agent("cemrl", config, make_env(task), EvaluationConfig())
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    key, actors_key = jax.random.split(jax.random.PRNGKey(1))
    actors = agent.sample(actors_key, state.cem)[:agent.num_trained]
    steps = config.pop_size * config.t_max
    programs = {
        "train_half": jax.jit(lambda s, a: agent.train_half(
            s.td3, s.buffer, key, a, jnp.asarray(steps))[1]),
        "one_after_the_other": jax.jit(lambda s, a: one_after_the_other(
            agent, s.td3, s.buffer, key, a, jnp.asarray(steps)))}
    half = agent.num_trained
    sequential = {"train_half": steps // half * half + steps,
                  "one_after_the_other": (steps // half + steps) * half}
    entry = {"task": task, "env_steps": steps, "actors_trained": half, "programs": {}}
    trained = {}
    for name, program in programs.items():
        start = time.perf_counter()
        trained[name] = np.asarray(program(state, actors))
        compile_s = time.perf_counter() - start
        runs = repeated_seconds(program, state, actors, repeats=repeats)
        entry["programs"][name] = {
            "compile_and_run_s": compile_s, "runs_s": runs, "median_s": float(np.median(runs)),
            "sequential_updates": sequential[name],
            "us_per_sequential_update": float(np.median(runs)) / sequential[name] * 1e6}
    entry["speed_up"] = (entry["programs"]["one_after_the_other"]["median_s"]
                         / entry["programs"]["train_half"]["median_s"])
    entry["max_abs_difference"] = float(np.abs(trained["train_half"]
                                               - trained["one_after_the_other"]).max())
    entry["max_abs_training_move"] = float(np.abs(trained["train_half"]
                                                  - np.asarray(actors)).max())
    return entry


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=["halfcheetah"])
    parser.add_argument("--t-max", nargs="*", type=int, default=[],
                        help="episode caps T_max to measure at (S = N·T_max; default: the "
                        "configuration's), e.g. to see the two orders drift apart with S")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each program")
    parser.add_argument("--out", help="default: benchmarks/results/cemrl_training.json; with "
                        "--smoke, the same name in a temporary directory")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    out = results_path(args.out, "benchmarks/results/cemrl_training.json", args.smoke)
    os.makedirs(out.parent, exist_ok=True)
    result = {**provenance(), "tasks": []}
    sizes = SMOKE_SIZES if args.smoke else {}
    caps = [dict(t_max=t, t_init=t) for t in args.t_max] or [{}]
    for task in args.tasks:
        for cap in caps:
            result["tasks"].append(measure(task, args.repeats, {**sizes, **cap}))
            print(json.dumps(result["tasks"][-1]), flush=True)
            out.write_text(json.dumps(result, indent=1))   # a cut-off run keeps those done


if __name__ == "__main__":
    main()

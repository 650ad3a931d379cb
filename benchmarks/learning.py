"""Learning results of one configuration on one task: seeds vmapped in one program.

Trains `--seeds` seeds of PGPS (the paper's configuration `for_task(task)` with `--set`
overrides, on the task's env with `--env` keyword arguments) for `--steps` env steps through
the CLI's loop (`pgps_jax.cli.loop`, the seeds vmapped), and writes a JSON with
- the μ evaluation curve of every seed (`eval/step`, `eval/mu_mean`, every 10,000 steps);
- μ, the TD3 actor and the elite at the end, each on 10 deterministic episodes from fresh
  start states (PRNGKey(10_000 + seed)), per seed;
- per generation and seed: episode limit T, interaction steps, population mean and elite
  return, the TD3 actor's return, whether the guided loss trained it, β and the CEM variance.

    python -m benchmarks.learning --task ant --steps 500000 --env start_pose=qpos0 \
        --set fell_behind_rule=mean_minus_std --out benchmarks/results/learning_ant_text.json
"""

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.timing import provenance
from pgps_jax.agent.config import EvaluationConfig, PGPSConfig, for_task
from pgps_jax.agent.pgps import PGPS
from pgps_jax.cli import loop
from pgps_jax.cli.assignments import assignments, env_assignments, field_types
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import make_env

PER_GENERATION = {"limit": "gen/episode_limit", "interaction_steps": "gen/interaction_steps",
                  "return_mean": "pop/return_mean", "elite_return": "cem/elite_return",
                  "td3_return": "td3/return", "guided": "td3/guided_loss", "beta": "td3/beta",
                  "cem_var": "cem/var_mean"}
FINAL_KEY_OFFSET = 10_000


def train(task: str, steps: int, seeds: int, overrides: dict, env_kwargs: dict) -> dict:
    agent = PGPS(for_task(task, **overrides), make_env(task, **env_kwargs), EvaluationConfig())
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    eval_keys = jax.vmap(lambda s: jax.random.PRNGKey(s + 100))(jnp.arange(seeds))
    start = time.perf_counter()
    programs = loop.Programs.compile(agent, keys, eval_keys, seeds=True)
    state = programs["init"](keys, eval_keys)
    curves = [[] for _ in range(seeds)]
    per_generation = {name: [] for name in PER_GENERATION}
    while int(np.min(jax.device_get(state.total_steps))) < steps:
        state, done = loop.generation(programs, state)
        m = done.metrics
        for seed in np.flatnonzero(m["eval/done"]):
            curves[seed].append((int(m["eval/step"][seed]), float(m["eval/mu_mean"][seed])))
        for name, key in PER_GENERATION.items():
            per_generation[name].append(np.asarray(m[key]).tolist())
        generation = len(per_generation["limit"])
        if generation % 20 == 0:
            print(f"generation {generation}: steps {np.asarray(m['gen/total_steps']).tolist()}"
                  f" μ {[c[-1][1] if c else None for c in curves]}"
                  f" ({time.perf_counter() - start:.0f} s)", flush=True)
    final_keys = jax.vmap(lambda s: jax.random.PRNGKey(s + FINAL_KEY_OFFSET))(jnp.arange(seeds))
    state, finished = loop.finish(programs, state, final_keys)
    for seed in np.flatnonzero(finished.unfinished_active):  # played from its start
        curves[seed].append((int(finished.unfinished_step[seed]),
                             float(finished.unfinished["eval/mu_mean"][seed])))
    return {"task": task, "steps": steps, "seeds": seeds, "overrides": overrides,
            "env": env_kwargs, "wall_s": time.perf_counter() - start,
            "final": {name: np.asarray(finished.final[f"eval/{name}_mean"]).tolist()
                      for name in agent.evaluated},
            "curves": curves, "per_generation": per_generation}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--set", nargs="*", default=[], action="extend", metavar="FIELD=VALUE",
                        help="PGPSConfig fields replacing the paper's")
    parser.add_argument("--env", nargs="*", default=[], action="extend", metavar="NAME=VALUE",
                        help="keyword arguments of make_env")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    try:
        overrides = assignments(args.set, "--set", field_types(PGPSConfig))
        env_kwargs = env_assignments(args.env)
    except UsageError as e:
        parser.error(str(e))
    result = train(args.task, args.steps, args.seeds, overrides, env_kwargs)
    result.update(provenance())
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f)
    final = result["final"]
    print(json.dumps({"task": args.task, "set": args.set, "env": args.env,
                      "wall_s": round(result["wall_s"]),
                      **{k: [round(x) for x in v] for k, v in final.items()}}))


if __name__ == "__main__":
    main()

"""Peer reference: Brax's own SAC for 1M env steps on the same task and GPU.

Runs `brax.training.agents.sac` on this project's MJX task (same model and solver settings as
PGPS trains on), with these settings: 64 envs, one gradient update per env
step (64 per 64 env steps), batch 256, 1000-step episodes, deterministic evaluation. Reports
the wall-clock including compilation and the evaluation returns.

Brax 0.14.2 calls `jax.device_put_replicated`, which current JAX has removed; it is mapped to
`jax.device_put` of the stacked tree here.

    python -m benchmarks.brax_sac --task halfcheetah --steps 1000000
"""

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp

from pgps_jax.envs import make_env


def _device_put_replicated(tree, devices):
    """Replicates `tree` on `devices` (one leading axis per device)."""
    stacked = jax.tree.map(lambda x: jnp.stack([jnp.asarray(x)] * len(devices)), tree)
    return jax.device_put(stacked, devices[0]) if len(devices) == 1 else jax.device_put(
        stacked, jax.sharding.PositionalSharding(devices).reshape(len(devices)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="halfcheetah")
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--num-evals", type=int, default=11)
    parser.add_argument("--out", default="benchmarks/results/brax_sac.json")
    parser.add_argument("--no-normalize", action="store_true",
                        help="feed raw observations (PGPS and TD3 do not normalise)")
    parser.add_argument("--env", nargs="*", default=[], metavar="NAME=VALUE",
                        help="keyword arguments of make_env (e.g. floor_contacts=every_geom)")
    args = parser.parse_args()
    env_kwargs = dict(item.split("=", 1) for item in args.env)
    if not hasattr(jax, "device_put_replicated"):
        jax.device_put_replicated = _device_put_replicated
    from brax.training.agents.sac import train as sac

    curve, start = [], time.perf_counter()

    def progress(step, metrics):
        curve.append({"step": int(step), "wall_s": time.perf_counter() - start,
                      "eval_return": float(metrics["eval/episode_reward"])})
        print(json.dumps(curve[-1]), flush=True)

    sac.train(environment=make_env(args.task, **env_kwargs), num_timesteps=args.steps, episode_length=1000,
              num_envs=64, num_eval_envs=16, batch_size=256, grad_updates_per_step=64,
              learning_rate=6e-4, discounting=0.99, reward_scaling=1.0,
              normalize_observations=not args.no_normalize, min_replay_size=8192,
              max_replay_size=min(args.steps, 1_000_000), num_evals=args.num_evals,
              deterministic_eval=True, seed=0, progress_fn=progress)
    result = {"device": jax.devices()[0].device_kind, "task": args.task, "steps": args.steps,
              "normalize_observations": not args.no_normalize, "env": env_kwargs,
              "wall_s_including_compile": time.perf_counter() - start,
              "first_progress_s (compile + first eval)": curve[0]["wall_s"], "curve": curve}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps({k: v for k, v in result.items() if k != "curve"}))


if __name__ == "__main__":
    main()

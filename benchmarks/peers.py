"""Peers from Brax: its SAC and PPO trained on this project's MJX tasks, written where the
paper experiments' report draws them beside PGPS and the baselines.

    python -m benchmarks.peers --algo sac --task halfcheetah            # 1M steps, seeds 1-5
    python -m benchmarks.peers --algo ppo --task hopper --seeds 3

Runs `brax.training.agents.<algo>.train` on `make_env(task)` (the model and solver settings
PGPS trains on) for `--steps` env steps per seed, one seed after the other, with the settings
below: Brax's published SAC and PPO settings for its MuJoCo tasks, with 1000-step episodes,
observation normalisation and a deterministic test of 16 episodes at each evaluation. Each
seed's curve goes to `<out>/figure4/<task>/brax_<algo>/seed<k>.csv` (Step, Mean, Std: Brax
reports the mean and std of its test episodes, not the episodes), and `result.json` holds the
final returns (the last evaluation, at the last multiple of the evaluation spacing within
`--steps`), the settings, the wall-clock per seed including
compilation and the device.

Brax 0.14.2 calls `jax.device_put_replicated`, which current JAX has removed; it is mapped to
`jax.device_put` of the stacked tree here.
"""

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp

from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.assignments import env_assignments
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import make_env

SETTINGS = {
    "sac": dict(episode_length=1000, num_envs=64, num_eval_envs=16, batch_size=256,
                grad_updates_per_step=64, learning_rate=6e-4, discounting=0.99,
                reward_scaling=1.0, normalize_observations=True, min_replay_size=8192,
                max_replay_size=1_000_000, deterministic_eval=True),
    "ppo": dict(episode_length=1000, num_envs=32, num_eval_envs=16, batch_size=32,
                num_minibatches=4, unroll_length=64, num_updates_per_batch=10,
                learning_rate=3e-4, entropy_cost=0.0, discounting=0.99, gae_lambda=0.95,
                clipping_epsilon=0.2, reward_scaling=1.0, normalize_observations=True,
                deterministic_eval=True),
}
"""SAC: one gradient update per env step (64 per step of the 64 envs), as Brax runs it on
its MuJoCo tasks. PPO: the PPO paper's MuJoCo settings for a 1M-step budget (Schulman et
al., 2017: learning rate 3e-4, γ 0.99, λ 0.95, clip 0.2, 10 epochs per batch) on 32 envs:
8,192 env steps per batch in 4 minibatches. Brax's own PPO settings for these tasks take
327,680 env steps per update, 3 updates in 1M."""


def env_steps_per_update(algo: str) -> int:
    """The env steps between two of the algorithm's training steps (Brax's granularity)."""
    s = SETTINGS[algo]
    if algo == "ppo":
        return s["batch_size"] * s["num_minibatches"] * s["unroll_length"]
    return s["num_envs"]


def evaluations(algo: str, steps: int, every: int) -> tuple[int, int]:
    """(num_evals for Brax, env steps between evaluations): about every `every` steps, on a
    multiple of the training step, so that the run takes `steps` env steps (not more)."""
    per_update = env_steps_per_update(algo)
    spacing = -(-every // per_update) * per_update
    return steps // spacing + 1, spacing


def _device_put_replicated(tree, devices):
    """Replicates `tree` on `devices` (one leading axis per device)."""
    stacked = jax.tree.map(lambda x: jnp.stack([jnp.asarray(x)] * len(devices)), tree)
    return jax.device_put(stacked, devices[0]) if len(devices) == 1 else jax.device_put(
        stacked, jax.sharding.PositionalSharding(devices).reshape(len(devices)))


def train_seed(algo: str, task: str, steps: int, seed: int, every: int,
               normalize: bool, env_kwargs: dict) -> tuple[list[list[float]], float]:
    """One seed: its evaluations [[Step, Mean, Std], ...] and its wall-clock in seconds."""
    if not hasattr(jax, "device_put_replicated"):
        jax.device_put_replicated = _device_put_replicated
    if algo == "sac":
        from brax.training.agents.sac import train as agent
    else:
        from brax.training.agents.ppo import train as agent
    rows, start = [], time.perf_counter()

    def progress(step, metrics):
        rows.append([int(step), float(metrics["eval/episode_reward"]),
                     float(metrics["eval/episode_reward_std"])])
        print(f"{algo} {task} seed {seed}: step {rows[-1][0]:,} return {rows[-1][1]:.1f} "
              f"({time.perf_counter() - start:.0f} s)", flush=True)

    settings = {**SETTINGS[algo], "normalize_observations": normalize}
    if algo == "sac":
        settings["max_replay_size"] = min(steps, settings["max_replay_size"])
    num_evals, spacing = evaluations(algo, steps, every)
    agent.train(environment=make_env(task, **env_kwargs), num_timesteps=(num_evals - 1) * spacing,
                num_evals=num_evals, seed=seed, progress_fn=progress, **settings)
    return rows, time.perf_counter() - start


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--algo", choices=sorted(SETTINGS), default="sac")
    parser.add_argument("--task", default="halfcheetah")
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--seeds", type=int, default=5, help="seeds 1..SEEDS, one at a time")
    parser.add_argument("--eval-every", type=int, default=10_000,
                        help="env steps between evaluations (rounded up to a multiple of the "
                             "algorithm's training step)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("benchmarks/results/paper"))
    parser.add_argument("--no-normalize", action="store_true",
                        help="feed raw observations (PGPS and TD3 do not normalise)")
    parser.add_argument("--env", nargs="*", default=[], metavar="NAME=VALUE",
                        help="keyword arguments of make_env (e.g. floor_contacts=gym)")
    args = parser.parse_args(argv)
    try:
        env_kwargs = env_assignments(args.env)
    except UsageError as e:
        parser.error(str(e))
    name = f"brax_{args.algo}"
    directory = args.out / "figure4" / args.task / name
    directory.mkdir(parents=True, exist_ok=True)
    finals, walls = [], []
    for seed in range(1, args.seeds + 1):
        rows, wall = train_seed(args.algo, args.task, args.steps, seed, args.eval_every,
                                not args.no_normalize, env_kwargs)
        rundir.write_csv(directory / f"seed{seed}.csv", ["", "Step", "Mean", "Std"],
                         [[i, *row] for i, row in enumerate(rows)])
        finals.append(rows[-1][1])
        walls.append(wall)
    result = {"task": args.task, "config": name, "algo": name, "steps": args.steps,
              "seeds": list(range(1, args.seeds + 1)),
              "env_steps": [int(rows[-1][0])] * args.seeds,
              "final": {"policy": finals}, "wall_s": sum(walls), "wall_s_per_seed": walls,
              "device": f"1 × {jax.devices()[0].device_kind}",
              "settings": {**SETTINGS[args.algo], "normalize_observations":
                           not args.no_normalize, "env": env_kwargs}}
    rundir.write_atomic(directory / "result.json", json.dumps(result, indent=1).encode())
    print(json.dumps({k: v for k, v in result.items() if k != "settings"}))


if __name__ == "__main__":
    main()

"""Peers from Brax: its SAC and PPO trained on this project's MJX tasks, written where the
paper experiments' report draws them beside PGPS and the baselines.

    python -m benchmarks.peers --algo sac --task halfcheetah            # 1M steps, seeds 1-5
    python -m benchmarks.peers --algo sac --task hopper --concurrent 5  # 5 seeds at once
    python -m benchmarks.peers --algo ppo --task hopper --seeds 3

Runs `brax.training.agents.<algo>.train` on `make_env(task)` (the model and solver settings
PGPS trains on) for `--steps` env steps per seed, with the settings below: Brax's published
SAC and PPO settings for its MuJoCo tasks, with 1000-step episodes, observation normalisation
and a deterministic test of 16 episodes at each evaluation. Seeds run one after the other, or
`--concurrent` at a time in processes of their own, placed on the visible GPUs as the
experiment runner places its cells (a seed's training is a chain of small kernels that leaves
a GPU mostly idle). Each seed's curve goes to `<out>/figure4/<task>/brax_<algo>/seed<k>.csv`
(Step, Mean, Std: Brax reports the mean and std of its test episodes, not the episodes) and
its final return (the last evaluation, at the last multiple of the evaluation spacing within
`--steps`), wall-clock, compilation included, and the settings it ran with (the options and
the task's physics) to `seed<k>.json`. A seed with its `seed<k>.json` is done and not run
again, so a cut-off command continues with the seeds it had not finished; a seed done with
other settings is refused, naming them. `result.json` gathers the seeds' records, the
settings and the device once every seed is done.

Brax 0.14.2 calls `jax.device_put_replicated`, which current JAX has removed; it is mapped to
`jax.device_put` of the stacked tree here.
"""

import argparse
import json
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp

from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.assignments import env_assignments
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import ALL_TASKS, make_env
from pgps_jax.experiments.paper.runner import (env_physics, physics_of,
                                                settings_differing)
from pgps_jax.experiments.paper.side_by_side import (MEMORY_FRACTION_OLD, memory_share,
                                                     placements)

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
    multiple of the training step, the last at the first of them to reach `steps` (as PGPS's
    final evaluation is at the generation that reaches it)."""
    per_update = env_steps_per_update(algo)
    spacing = -(-every // per_update) * per_update
    return -(-steps // spacing) + 1, spacing


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


def run_seed(algo: str, task: str, steps: int, seed: int, every: int, normalize: bool,
             env_kwargs: dict, directory: pathlib.Path, concurrent: int, settings: dict
             ) -> None:
    """Trains one seed and writes its curve and its record (final return, wall-clock, and
    `settings`, those it ran with: `run_settings`)."""
    rows, wall = train_seed(algo, task, steps, seed, every, normalize, env_kwargs)
    rundir.write_csv(directory / f"seed{seed}.csv", ["", "Step", "Mean", "Std"],
                     [[i, *row] for i, row in enumerate(rows)])
    record = {"seed": seed, "env_steps": int(rows[-1][0]), "final": rows[-1][1], "wall_s": wall,
              "device": f"1 × {jax.devices()[0].device_kind}", "concurrent": concurrent,
              "run": settings}
    rundir.write_atomic(directory / f"seed{seed}.json", json.dumps(record).encode())


def run_settings(task: str, steps: int, every: int, normalize: bool, env_kwargs: dict
                 ) -> dict:
    """What a seed's record must match for the seed to count as done by this command: the
    options, and the task's physics (`MjxEnv.settings`) that they and the package give (the
    `--env` arguments count through it alone, as in the experiment runner)."""
    return {"--steps": steps, "--eval-every": every, "--no-normalize": not normalize,
            "--env": env_kwargs, "physics": env_physics(make_env(task, **env_kwargs))}


def done_seeds(directory: pathlib.Path, task: str, seeds: list[int], settings: dict
               ) -> list[int]:
    """The seeds of `seeds` whose records exist; UsageError if one of them ran with other
    settings (naming the option, what it ran with and what this command asks)."""
    done = []
    for seed in seeds:
        path = directory / f"seed{seed}.json"
        if not path.exists():
            continue
        ran = json.loads(path.read_text()).get("run")
        if ran is None:
            raise UsageError(f"seed {seed} in {directory} has a record from before records "
                             "held their settings: use another --out, or remove the seed's "
                             "files to run it again")
        recorded = {"physics": ran["physics"]} if "physics" in ran else {}  # older: none
        ran = {**ran, "physics": physics_of({"env": ran["--env"], **recorded}, task)}
        differ = settings_differing(ran, settings, "--env")
        if differ:
            option = differ[0]
            raise UsageError(f"seed {seed} in {directory} ran with {option} "
                             f"{ran.get(option)!r}, this command asks {settings[option]!r}: "
                             "use the settings it ran with, or another --out")
        done.append(seed)
    return done


def run_concurrently(argv: list[str], seeds: list[int], concurrent: int,
                     memory: float) -> list[str]:
    """Runs each of `seeds` as this command with `--seed k`, `concurrent` at a time in processes
    of their own, dividing the `memory` share of each GPU's memory (`memory_share`); returns
    what the failed ones said (their last lines of stderr). The children end with this
    command, however it ends."""
    slots = placements(min(concurrent, len(seeds)), jax.default_backend(),
                       jax.local_device_count(), os.environ.get("CUDA_VISIBLE_DEVICES"), memory)
    inherited = {k: v for k, v in os.environ.items()
                 if k not in (MEMORY_FRACTION_OLD, "XLA_PYTHON_CLIENT_PREALLOCATE")}
    waiting, running, failures = list(seeds), {}, []
    terminate = signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    try:
        while waiting or running:
            for slot in range(len(slots)):
                if slot not in running and waiting:
                    seed, said = waiting.pop(0), tempfile.TemporaryFile()
                    running[slot] = seed, said, subprocess.Popen(
                        [sys.executable, "-m", "benchmarks.peers", *argv, "--seed", str(seed),
                         "--concurrent", str(concurrent)], env={**inherited, **slots[slot]},
                        stderr=said)
            time.sleep(1)
            for slot, (seed, said, child) in list(running.items()):
                if child.poll() is not None:
                    del running[slot]
                    if child.returncode != 0:
                        said.seek(0)
                        lines = said.read().decode(errors="replace").rstrip().splitlines()
                        failures.append(f"seed {seed}: " + " | ".join(lines[-3:]))
                    said.close()
    finally:  # an error, Ctrl-C or SIGTERM here: the seeds under way stop with this command
        for seed, said, child in running.values():
            child.terminate()
            child.wait()
            said.close()
        signal.signal(signal.SIGTERM, terminate)
    return failures


def gather(directory: pathlib.Path, seeds: list[int], name: str, args, env_kwargs: dict) -> dict:
    """`result.json` from the seeds' records: final returns, env steps, wall-clocks, settings."""
    records = [json.loads((directory / f"seed{seed}.json").read_text()) for seed in seeds]
    result = {"task": args.task, "config": name, "algo": name, "steps": args.steps,
              "seeds": seeds, "env_steps": [r["env_steps"] for r in records],
              "final": {"policy": [r["final"] for r in records]},
              "wall_s": sum(r["wall_s"] for r in records),  # of the seeds, one after another
              "wall_s_per_seed": [r["wall_s"] for r in records],
              "concurrent": [r["concurrent"] for r in records],
              "device": sorted({r["device"] for r in records}),
              "settings": {**SETTINGS[args.algo], "normalize_observations":
                           not args.no_normalize, "env": env_kwargs}}
    rundir.write_atomic(directory / "result.json", json.dumps(result, indent=1).encode())
    return result


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--algo", choices=sorted(SETTINGS), default="sac")
    parser.add_argument("--task", default="halfcheetah", choices=ALL_TASKS)
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--seeds", type=int, default=5, help="seeds 1..SEEDS")
    parser.add_argument("--seed", type=int, help="this seed alone (its curve and record; no "
                        "result.json)")
    parser.add_argument("--concurrent", type=int, default=1,
                        help="seeds at a time, each in a process of its own")
    parser.add_argument("--eval-every", type=int, default=10_000,
                        help="env steps between evaluations (rounded up to a multiple of the "
                             "algorithm's training step)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("benchmarks/results/paper"))
    parser.add_argument("--no-normalize", action="store_true",
                        help="feed raw observations (PGPS and TD3 do not normalise)")
    parser.add_argument("--env", nargs="*", default=[], action="extend", metavar="NAME=VALUE",
                        help="keyword arguments of make_env (e.g. floor_contacts=gym)")
    args = parser.parse_args(argv)
    try:
        env_kwargs = env_assignments(args.env)
    except UsageError as e:
        parser.error(str(e))
    for option in ("seeds", "seed", "concurrent"):
        if getattr(args, option) is not None and getattr(args, option) < 1:
            parser.error(f"--{option} must be a positive integer")
    name = f"brax_{args.algo}"
    directory = args.out / "figure4" / args.task / name
    directory.mkdir(parents=True, exist_ok=True)
    seeds = [args.seed] if args.seed is not None else list(range(1, args.seeds + 1))
    if args.seed is None and args.concurrent > 1:
        # this process only builds the env and asks which devices there are: it leaves their
        # memory to the seeds
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    try:
        settings = run_settings(args.task, args.steps, args.eval_every, not args.no_normalize,
                                env_kwargs)
    except (TypeError, ValueError) as e:  # --env names that the task does not take, say
        parser.error(f"--env {' '.join(args.env)}: {e}")
    try:
        done = done_seeds(directory, args.task, seeds, settings)
        memory = memory_share(os.environ)
    except UsageError as e:
        parser.error(str(e))
    to_run = [seed for seed in seeds if seed not in done]
    if args.concurrent > 1 and len(to_run) > 1:
        failures = run_concurrently(argv, to_run, args.concurrent, memory)
        if failures:
            print(f"error: {len(failures)} seed(s) failed: " + "; ".join(failures),
                  file=sys.stderr)
            return 1
    else:
        for seed in to_run:
            run_seed(args.algo, args.task, args.steps, seed, args.eval_every,
                     not args.no_normalize, env_kwargs, directory, args.concurrent, settings)
    if args.seed is None:
        result = gather(directory, seeds, name, args, env_kwargs)
        print(json.dumps({k: v for k, v in result.items() if k != "settings"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

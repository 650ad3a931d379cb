"""Experiments per GPU-hour: the cost of a seed against the seeds vmapped in one program, and
the wall-clock of a grid of cells run side by side.

`seeds`: per task, one late-run generation (T = T_max, Q-filtering active, the paper's
configuration) of S seeds vmapped in one program, for each S; its time, and the cost per seed
relative to the fewest seeds measured (by default one alone: 1.0; S seeds for the price of one:
1/S).

`grid`: the Figure-4 PGPS cells through `python -m pgps_jax.experiments.paper figure4
--configs pgps --concurrent K` (K cells at a time in processes of their own, placed on the
visible GPUs in turn; CUDA's MPS daemon is recorded as running or not), timed from the
command's start to its end, with each cell's own wall-clock from its `result.json` (a cell
run in parts, `--seeds-per-program S`, sums its parts': each part is then a process of its
own, and K counts parts).

    python -m benchmarks.grid_throughput seeds --tasks halfcheetah hopper --seeds 1 5 10 25 50
    python -m benchmarks.grid_throughput grid --concurrent 5 --out runs/grid
    python -m benchmarks.grid_throughput grid --tasks walker2d hopper --seeds-per-program 1 \
        --concurrent 10 --out runs/grid_parts
    python -m benchmarks.grid_throughput seeds --smoke    # tiny sizes: a CPU check of the script

Entries are appended to `benchmarks/results/grid_throughput.json` after each measurement (a
`seeds` entry is rewritten after each seed count).
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time
from typing import Iterator, Optional

import jax
import jax.numpy as jnp

from benchmarks.timing import physics_record, provenance, results_path, timed
from pgps_jax.agent.config import EvaluationConfig, for_task
from pgps_jax.agent.pgps import PGPS
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.assignments import env_assignments
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import TASKS, make_env

RESULTS = pathlib.Path("benchmarks/results/grid_throughput.json")
SMOKE = dict(pop_size=2, top_k=1, actor_hidden=(16,), critic_hidden=(16,), batch_size=16,
             buffer_size=2000, warmup_steps=200, t_init=20, t_max=40, t_interval=400,
             q_filter_start=400, sample_ratio=4, ss1_size=8, ss2_size=16)
"""A tiny PGPS for --smoke (the tests' reduced configuration)."""


def late_run_steps(config) -> int:
    """The fewest env steps at which the episode limit is T_max and Q-filtering is on."""
    increments = -(-(config.t_max - config.t_init) // config.t_increment)
    return max(config.q_filter_start, increments * config.t_interval)


def seeds_cost(task: str, seed_counts: list[int], smoke: bool, env_kwargs: dict
               ) -> Iterator[dict]:
    """One late-run generation of S seeds vmapped, for each S in `seed_counts`, on the physics
    `make_env(task, **env_kwargs)` gives; yields the task's entry after each S (so a run cut
    short keeps the counts it measured)."""
    config = for_task(task, **(SMOKE if smoke else {}))
    env = make_env(task, **env_kwargs)
    agent = PGPS(config, env, EvaluationConfig())
    late = late_run_steps(config)
    step = jax.jit(jax.vmap(agent.generation_step))
    rows = []
    for seeds in seed_counts:
        keys = jax.random.split(jax.random.PRNGKey(0), seeds)
        state = jax.jit(jax.vmap(agent.init))(keys, keys)
        state = state.replace(  # no test evaluation falls due: the generation alone
            total_steps=jnp.full((seeds,), late, jnp.int32),
            evaluation=state.evaluation.replace(
                next_due=jnp.full((seeds,), 2**30, jnp.int32)))
        compile_s, generation_s = timed(step, state, repeats=3)
        fewest = rows[0]["generation_s"] / rows[0]["seeds"] if rows else generation_s / seeds
        rows.append({"seeds": seeds, "generation_s": generation_s, "compile_and_run_s": compile_s,
                     # against the first (fewest) seed count: 1 by default
                     "cost_per_seed_vs_fewest": generation_s / seeds / fewest})
        yield {"kind": "seeds", "task": task, "physics": physics_record(env),
               "pop_size": config.pop_size, "T": config.t_max, "env_steps_at": late,
               "rows": list(rows)}


def mps_running() -> bool:
    """Whether CUDA's MPS control daemon runs among the processes this one can see."""
    for status in pathlib.Path("/proc").glob("[0-9]*/comm"):
        try:
            if status.read_text().strip() == "nvidia-cuda-mps":
                return True
        except OSError:
            continue
    return False


def grid(tasks: list[str], concurrent: int, out: pathlib.Path, steps: int, seeds: int,
         smoke: bool, environ: dict, seeds_per_program: Optional[int] = None) -> dict:
    """The Figure-4 PGPS cells of `tasks`, `concurrent` programs at a time (cells, or parts of
    `seeds_per_program` seeds), into `out` (which must not hold them yet: a done cell would
    not run again, a cut-off one would continue)."""
    held = [t for t in tasks if (out / "figure4" / t / "pgps").exists()]
    if held:
        sys.exit(f"{out} already holds cells of {', '.join(held)}: use another --out")
    command = [sys.executable, "-m", "pgps_jax.experiments.paper", "figure4", "--configs",
               "pgps", "--tasks", *tasks, "--concurrent", str(concurrent), "--steps",
               str(steps), "--seeds", str(seeds), "--out", str(out), "--no-progress"]
    if seeds_per_program is not None:
        command += ["--seeds-per-program", str(seeds_per_program)]
    if smoke:
        command += ["--set", *(f"{k}={list(v) if isinstance(v, tuple) else v}"
                               for k, v in SMOKE.items()),
                    "--eval", "every=200", "episodes=2", "steps=50"]
    start = time.perf_counter()
    subprocess.run(command, check=True, env=environ)
    wall = time.perf_counter() - start
    cells = []
    for task in tasks:
        result = json.loads((out / "figure4" / task / "pgps" / "result.json").read_text())
        cells.append({"task": task, "wall_s": result["wall_s"], "device": result["device"],
                      "final_mu": result["final"]["mu"],
                      "parts_wall_s": [part["wall_s"] for part in result.get("parts", [])]})
    return {"kind": "grid", "tasks": tasks, "concurrent": concurrent, "steps": steps,
            "seeds": seeds, "seeds_per_program": seeds_per_program or seeds,
            "gpus": jax.local_device_count(), "mps": mps_running(), "wall_s": wall,
            "cells": cells}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("measure", choices=["seeds", "grid"])
    parser.add_argument("--tasks", nargs="*", default=list(TASKS))
    parser.add_argument("--seeds", nargs="*", type=int, default=[1, 5, 10, 25, 50],
                        help="seeds: the seed counts measured")
    parser.add_argument("--grid-seeds", type=int, default=5, help="grid: each cell's seeds")
    parser.add_argument("--concurrent", type=int, default=5,
                        help="grid: programs at a time (cells, or parts with --seeds-per-program)")
    parser.add_argument("--seeds-per-program", type=int, default=None, metavar="S",
                        help="grid: each cell's seeds S to a program (default: all in one)")
    parser.add_argument("--env", nargs="*", default=[], metavar="NAME=VALUE",
                        help="seeds: physics settings (`make_env`'s arguments), e.g. "
                        "fused_solve=false matmul_precision=default")
    parser.add_argument("--steps", type=int, default=1_000_000, help="grid: each cell's budget")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/grid"))
    parser.add_argument("--results", help=f"default: {RESULTS}; with --smoke, the same name in a "
                        "temporary directory")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    if args.measure == "grid" and args.env:
        parser.error("--env applies to `seeds`; the grid's cells run on the physics the "
                     "experiment runner gives them")
    try:
        env_kwargs = env_assignments(args.env)
    except UsageError as e:
        parser.error(str(e))
    args.results = results_path(args.results, str(RESULTS), args.smoke)
    environ = dict(os.environ)
    if args.measure == "grid":  # this process only times: the GPUs' memory is the cells'
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    header = provenance()
    saved = json.loads(args.results.read_text()) if args.results.exists() else []

    def record(entry: dict, replacing_last: bool = False) -> None:
        if replacing_last:
            saved.pop()
        saved.append({**header, **entry})
        print(json.dumps(saved[-1]), flush=True)
        args.results.parent.mkdir(parents=True, exist_ok=True)
        rundir.write_atomic(args.results, json.dumps(saved, indent=1).encode())

    if args.measure == "seeds":
        for task in args.tasks:
            for measured, entry in enumerate(seeds_cost(task, args.seeds, args.smoke,
                                                        env_kwargs)):
                record(entry, replacing_last=measured > 0)
    else:
        record(grid(args.tasks, args.concurrent, args.out, args.steps if not args.smoke else 600,
                    args.grid_seeds, args.smoke, environ, args.seeds_per_program))


if __name__ == "__main__":
    main()

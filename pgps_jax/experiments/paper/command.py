"""`python -m pgps_jax.experiments.paper <experiment>`: run an experiment's cells in turn.

    python -m pgps_jax.experiments.paper figure4                      # 5 tasks × 5 seeds, 1M steps
    python -m pgps_jax.experiments.paper table1 --tasks ant --seeds 10
    python -m pgps_jax.experiments.paper figure4 --steps 20000 --set pop_size=4 --out /tmp/p

Results go to `<out>/<experiment>/<task>/<config>/` (`runner`), and the final returns of every
done cell to `<out>/<experiment>/final_returns.csv`. Run the same command again to continue:
done cells are skipped and a cut-off cell continues from its last checkpoint.
"""

import argparse
import ast
import pathlib
import sys

import numpy as np
from tqdm import tqdm

from pgps_jax.agent.config import EVALUATED_ACTORS, EvaluationConfig, PGPSConfig, for_task
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.errors import UsageError, report
from pgps_jax.experiments.paper.grid import EXPERIMENTS, Cell, cells
from pgps_jax.experiments.paper.runner import Budget, run_cell

OUT = pathlib.Path("benchmarks/results/paper")
FINAL_RETURNS = "final_returns.csv"


def cell_directory(out: pathlib.Path, experiment: str, cell: Cell) -> pathlib.Path:
    return out / experiment / cell.task / cell.config


def run(experiment: str, out: pathlib.Path, budget: Budget, tasks=(), configs=(),
        progress: bool = True) -> list[dict]:
    """Runs every cell of `experiment` (those of `tasks` and `configs` where given) and writes
    the table of final returns; returns the cells' results."""
    try:
        chosen = cells(experiment, tuple(tasks), tuple(configs))
    except ValueError as e:
        raise UsageError(str(e)) from None
    for cell in chosen:  # every configuration is valid before any cell runs
        try:
            for_task(cell.task, **dict(cell.overrides), **dict(budget.overrides))
        except TypeError:
            unknown = sorted(set(dict(budget.overrides)) - set(PGPSConfig.__dataclass_fields__))
            raise UsageError(f"--set: unknown PGPSConfig field {', '.join(unknown)}; valid: "
                             f"{', '.join(PGPSConfig.__dataclass_fields__)}") from None
        except ValueError as e:
            raise UsageError(f"{cell.task} {cell.config}: {e}") from None
    results = []
    for cell in chosen:
        with tqdm(total=budget.steps * budget.seeds, unit="step", unit_scale=True,
                  disable=not progress, desc=f"{experiment} {cell.task} {cell.config}") as bar:
            def advanced(generation, steps):
                bar.update(int(np.minimum(steps, budget.steps).sum()) - bar.n)
                bar.set_postfix_str(f"gen {generation}", refresh=False)
            results.append(run_cell(cell, cell_directory(out, experiment, cell), budget,
                                    advanced))
    write_final_returns(out / experiment / FINAL_RETURNS, results)
    return results


def write_final_returns(path: pathlib.Path, results: list[dict]) -> None:
    """One row per cell and seed: the final test return of μ, the TD3 actor and the elite."""
    header = ["task", "config", "seed", "env_steps"] + [f"{a}_final" for a in EVALUATED_ACTORS]
    lines = [",".join(header)]
    for r in results:
        for i, seed in enumerate(r["seeds"]):
            row = [r["task"], r["config"], seed, r["env_steps"][i]]
            row += [r["final"][a][i] for a in EVALUATED_ACTORS]
            lines.append(",".join(rundir.cell(v) for v in row))
    path.parent.mkdir(parents=True, exist_ok=True)
    rundir.write_atomic(path, ("\n".join(lines) + "\n").encode())


def _assignments(pairs: list[str], what: str) -> dict:
    """`name=value` pairs, values as Python literals where they parse, else strings."""
    values = {}
    for pair in pairs:
        name, sep, text = pair.partition("=")
        if not sep or not name:
            raise UsageError(f"{what} {pair!r} is not NAME=VALUE")
        try:
            values[name] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            values[name] = text
    return values


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pgps_jax.experiments.paper",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("experiment", help=", ".join(EXPERIMENTS))
    parser.add_argument("--tasks", nargs="*", default=[])
    parser.add_argument("--configs", nargs="*", default=[])
    parser.add_argument("--steps", type=int, default=Budget.steps)
    parser.add_argument("--seeds", type=int, default=Budget.seeds)
    parser.add_argument("--checkpoint-every", type=int, default=Budget.checkpoint_every,
                        help="generations between checkpoints")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="PGPSConfig fields replacing every cell's")
    parser.add_argument("--eval", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="EvaluationConfig fields (every, episodes, steps)")
    parser.add_argument("--out", type=pathlib.Path, default=OUT)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)

    def body() -> int:
        for name in ("steps", "seeds", "checkpoint_every"):
            if getattr(args, name) <= 0:
                raise UsageError(f"--{name.replace('_', '-')} must be a positive integer")
        try:
            budget = Budget(steps=args.steps, seeds=args.seeds,
                            evaluation=EvaluationConfig(**_assignments(args.eval, "--eval")),
                            checkpoint_every=args.checkpoint_every,
                            overrides=tuple(_assignments(args.set, "--set").items()))
        except TypeError as e:
            raise UsageError(f"--eval: {e}; valid: every, episodes, steps") from None
        except ValueError as e:
            raise UsageError(str(e)) from None
        run(args.experiment, args.out, budget, args.tasks, args.configs,
            progress=not args.no_progress)
        return 0

    return report(body)


if __name__ == "__main__":
    sys.exit(main())

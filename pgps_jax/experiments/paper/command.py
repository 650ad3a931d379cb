"""`python -m pgps_jax.experiments.paper <experiment>`: run the cells of an experiment.

    python -m pgps_jax.experiments.paper figure4                      # 5 tasks × 5 seeds, 1M steps
    python -m pgps_jax.experiments.paper table1 --tasks ant --seeds 10
    python -m pgps_jax.experiments.paper figure4 --steps 20000 --set pop_size=4 --out runs/paper
    python -m pgps_jax.experiments.paper figure4 --tasks ant --env floor_contacts=model \
        integrator=euler iterations=1 --out runs/ant_brax_physics
    python -m pgps_jax.experiments.paper figure4 --concurrent 5   # 5 cells at once, own processes
    python -m pgps_jax.experiments.paper figure4 --tasks ant --seeds-per-program 1 --concurrent 5
    python -m pgps_jax.experiments.paper figure4 --report         # tables and figures only

Results go to `<out>/<experiment>/<task>/<config>/` (`runner`), the final returns of every
done cell to `<out>/<experiment>/final_returns.csv`, and the figures and the table of the
report (`report`) beside it. Run the same command again to continue:
done cells are skipped and a cut-off cell continues from its last checkpoint; a done cell
given more `--seeds` runs only the seeds it has not done. With `--seeds-per-program S` a
cell's seeds run S to a program, in parts that run in turn or, with `--concurrent`, side by
side like cells.
"""

import argparse
import json
import os
import pathlib
import sys
from typing import Optional

import numpy as np
from tqdm import tqdm

from pgps_jax.agent.config import (SWITCHES, EvaluationConfig, PGPSConfig, check_for_algorithm,
                                    for_task)
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.assignments import assignments, env_assignments, field_types
from pgps_jax.cli.errors import EXIT_INTERRUPTED, UsageError, print_error, report
from pgps_jax.cli.stop_request import sigterm_as_ctrl_c
from pgps_jax.envs import make_env
from pgps_jax.experiments.paper import side_by_side
from pgps_jax.experiments.paper.grid import EXPERIMENTS, Cell, cells
from pgps_jax.experiments.paper.report import REFERENCE, sample_std, write_report
from pgps_jax.experiments.paper.runner import (RESULT, Budget, Seeds, done_seeds, parts,
                                               run_cell)

OUT = pathlib.Path("benchmarks/results/paper")
FINAL_RETURNS = "final_returns.csv"


def cell_directory(out: pathlib.Path, experiment: str, cell: Cell) -> pathlib.Path:
    return out / experiment / cell.task / cell.config


def run(experiment: str, out: pathlib.Path, budget: Budget, tasks=(), configs=(),
        progress: bool = True, reference: pathlib.Path = REFERENCE, concurrent: int = 1,
        child_environ: Optional[dict] = None) -> list[dict]:
    """Runs every cell of `experiment` (those of `tasks` and `configs` where given) and writes
    the table of final returns and the report (`reference`: the authors' curves); returns the
    cells' results, in the order of `tasks` where given. With `concurrent` > 1, that many
    cells, or parts of cells (`Budget.seeds_per_program`), at a time, each in a process of its
    own (`side_by_side`; `child_environ`: their environment, by default this process's)."""
    try:
        chosen = cells(experiment, tuple(tasks), tuple(configs))
    except ValueError as e:
        raise UsageError(str(e)) from None
    for task in dict.fromkeys(cell.task for cell in chosen):
        if budget.env:
            try:
                make_env(task, **dict(budget.env))
            except ValueError as e:
                raise UsageError(f"--env on {task}: {e}") from None
    for cell in chosen:  # every configuration is valid before any cell runs
        clash = sorted(set(cell.overrides) & set(dict(budget.overrides)))
        if clash:
            raise UsageError(f"--set {', '.join(clash)}: the {experiment} cell {cell.task} "
                             f"{cell.config} sets it itself")
        couplings = sorted(set(SWITCHES) & set(dict(budget.overrides)))
        if couplings and cell.algo != "pgps":
            raise UsageError(f"--set {', '.join(couplings)}: PGPS's couplings; the "
                             f"{experiment} cell {cell.task} {cell.config} has none of them "
                             f"(choose --configs pgps)")
        try:
            config = for_task(cell.task, cell.algo, **dict(cell.overrides),
                              **dict(budget.overrides))
            check_for_algorithm(cell.algo, config)
        except ValueError as e:
            raise UsageError(f"{cell.task} {cell.config}: {e}") from None
        if budget.steps <= config.warmup_steps:
            raise UsageError(f"--steps {budget.steps} does not exceed the random warm-up "
                             f"(warmup_steps={config.warmup_steps})")
    require_reference(reference)
    try:
        if concurrent > 1:
            results = _run_side_by_side(experiment, out, budget, chosen, concurrent, progress,
                                        dict(os.environ if child_environ is None
                                             else child_environ))
        else:
            results = [_run_in_turn(experiment, out, budget, cell, progress) for cell in chosen]
    except BaseException:
        _summarise(experiment, out, reference, failing=True)
        raise
    _summarise(experiment, out, reference)
    return results


def cell_summary(experiment: str, result: dict) -> str:
    """One line of a done cell: its seeds' final returns, mean ± sample std per actor."""
    finals = "; ".join(f"{actor} {np.mean(r):,.1f} ± {sample_std(r):,.1f}"
                       for actor, r in ((a, np.asarray(v)) for a, v in result["final"].items()))
    return (f"{experiment} {result['task']} {result['config']}: seeds "
            f"{', '.join(map(str, result['seeds']))} done at {min(result['env_steps']):,} env "
            f"steps or more; final {finals}")


def _summarise(experiment: str, out: pathlib.Path, reference: pathlib.Path,
               failing: bool = False) -> None:
    """`write_summary` of every done cell, whatever became of the others; while the run
    fails (`failing`), a failure to draw them is only warned of, so that the run's own error
    is the one reported."""
    if not any((out / experiment).glob(f"*/*/{RESULT}")):
        return
    try:
        write_summary(experiment, out, reference)
    except Exception as e:
        if not failing:
            raise
        print(f"warning: the tables and figures of the done cells were not drawn: {e}",
              file=sys.stderr)


def _units(out: pathlib.Path, experiment: str, budget: Budget, cell: Cell) -> list[Seeds]:
    """What runs of `cell`: its parts (`parts`), the whole cell where it is done, or the
    seeds it is given beyond those it has done."""
    return parts(budget, done_seeds(cell_directory(out, experiment, cell)))


def _run_in_turn(experiment: str, out: pathlib.Path, budget: Budget, cell: Cell,
                 progress: bool) -> dict:
    """Runs `cell` in this process, part after part, with a progress bar of its own."""
    directory = cell_directory(out, experiment, cell)
    reached = {}
    with tqdm(total=budget.steps * budget.seeds, unit="step", unit_scale=True,
              disable=not progress, desc=f"{experiment} {cell.task} {cell.config}") as bar:
        for part in _units(out, experiment, budget, cell):
            def advanced(generation, steps, part=part):
                reached[part.first] = int(np.minimum(steps[:part.count], budget.steps).sum())
                bar.update(sum(reached.values()) - bar.n)
                bar.set_postfix_str(f"gen {generation}", refresh=False)
            result = run_cell(cell, directory, budget, advanced, part)
            advanced(result["generations"], np.asarray(result["env_steps"]))  # done before
        return json.loads((directory / RESULT).read_text())


def _run_side_by_side(experiment: str, out: pathlib.Path, budget: Budget, chosen, concurrent,
                      progress: bool, environ: dict) -> list[dict]:
    """Runs the cells, or their parts, `concurrent` at a time in processes of their own, with
    one progress bar over all of them."""
    import jax
    units = [(cell, part) for cell in chosen for part in _units(out, experiment, budget, cell)]
    slots = side_by_side.placements(min(concurrent, len(units)), jax.default_backend(),
                                    jax.local_device_count(),
                                    environ.get("CUDA_VISIBLE_DEVICES"),
                                    side_by_side.memory_share(environ))
    reached = {}
    with tqdm(total=budget.steps * budget.seeds * len(chosen), unit="step", unit_scale=True,
              disable=not progress, desc=f"{experiment}: {len(units)} programs, "
              f"{len(slots)} at a time") as bar:
        def advanced(cell, part, generation, steps):
            reached[cell.task, cell.config, part.first] = int(
                np.minimum(np.asarray(steps)[:part.count], budget.steps).sum())
            bar.update(sum(reached.values()) - bar.n)
        side_by_side.run_side_by_side(
            experiment, budget, units, lambda c: cell_directory(out, experiment, c),
            slots, environ, advanced)
    return [json.loads((cell_directory(out, experiment, cell) / RESULT).read_text())
            for cell in chosen]


def require_reference(reference: pathlib.Path) -> None:
    """UsageError unless the folder of the authors' curves exists."""
    if not reference.is_dir():
        raise UsageError(f"--reference {reference}: no such folder (the authors' curves, "
                         "<task>/<seed>.csv; run from the repository's root or name it)")


def write_summary(experiment: str, out: pathlib.Path, reference: pathlib.Path
                  ) -> list[pathlib.Path]:
    """The table of final returns of the done cells of `experiment` under `out`
    (`FINAL_RETURNS`, if any is done) and the report of every cell with results there;
    returns the paths written (UsageError from `write_report` if there are none)."""
    done = [json.loads(p.read_text())
            for p in sorted((out / experiment).glob(f"*/*/{RESULT}"))]
    table = out / experiment / FINAL_RETURNS
    if done:
        write_final_returns(table, done)
    return ([table] if done else []) + write_report(experiment, out, reference)


def write_final_returns(path: pathlib.Path, results: list[dict]) -> None:
    """One row per done cell and seed: the final test return of each actor its algorithm
    evaluates (μ, the TD3 actor, the elite; empty where it has none), in columns of a fixed
    order whichever cells are done."""
    actors = sorted({a for r in results for a in r["final"]})
    header = ["task", "config", "seed", "env_steps"] + [f"{a}_final" for a in actors]
    rows = [[r["task"], r["config"], seed, r["env_steps"][i],
             *(r["final"][a][i] if a in r["final"] else "" for a in actors)]
            for r in results for i, seed in enumerate(r["seeds"])]
    path.parent.mkdir(parents=True, exist_ok=True)
    rundir.write_csv(path, header, rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pgps_jax.experiments.paper",
                                     description=__doc__.split("\n")[0],
                                     epilog="--tasks, --configs, --set, --eval and --env add "
                                            "up when repeated; a field given twice takes "
                                            "its last value.")
    parser.add_argument("experiment", help=", ".join(EXPERIMENTS))
    parser.add_argument("--tasks", nargs="*", default=[], action="extend")
    parser.add_argument("--configs", nargs="*", default=[], action="extend")
    parser.add_argument("--steps", type=int, default=Budget.steps)
    parser.add_argument("--seeds", type=int, default=Budget.seeds)
    parser.add_argument("--seeds-per-program", type=int, default=None, metavar="S",
                        help="seeds vmapped in one program (default: all of a cell's); a "
                             "cell of more runs in parts, side by side with --concurrent")
    parser.add_argument("--checkpoint-every", type=int, default=Budget.checkpoint_every,
                        help="generations between checkpoints, besides --checkpoint-every-s "
                             "(default: by time alone)")
    parser.add_argument("--checkpoint-every-s", type=float,
                        default=Budget.checkpoint_every_s, metavar="SECONDS",
                        help="seconds between checkpoints (default %(default)g)")
    parser.add_argument("--set", nargs="*", default=[], action="extend", metavar="FIELD=VALUE",
                        help="PGPSConfig fields replacing every cell's")
    parser.add_argument("--eval", nargs="*", default=[], action="extend", metavar="FIELD=VALUE",
                        help="EvaluationConfig fields (every, episodes, steps)")
    parser.add_argument("--env", nargs="*", default=[], action="extend", metavar="NAME=VALUE",
                        help="make_env keyword arguments: start_pose or Physics fields "
                             "(iterations, floor_contacts, ...)")
    parser.add_argument("--out", type=pathlib.Path, default=OUT)
    parser.add_argument("--concurrent", type=int, default=1, metavar="K",
                        help="cells in flight at a time, each in a process of its own, placed "
                             "on the GPUs in turn (default 1: in turn, in this process, each "
                             "cell's seeds split over every GPU)")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--report", action="store_true",
                        help="only draw the figures and tables from the results under --out")
    parser.add_argument("--reference", type=pathlib.Path, default=REFERENCE,
                        help="the authors' published curves, <task>/<seed>.csv")
    args = parser.parse_args(argv)

    def body() -> int:
        if args.report:
            try:
                cells(args.experiment)
            except ValueError as e:
                raise UsageError(str(e)) from None
            require_reference(args.reference)
            for path in write_summary(args.experiment, args.out, args.reference):
                print(path)
            return 0
        for name in ("steps", "seeds", "checkpoint_every", "concurrent", "seeds_per_program"):
            if getattr(args, name) is not None and getattr(args, name) <= 0:
                raise UsageError(f"--{name.replace('_', '-')} must be a positive integer")
        if not 0 < args.checkpoint_every_s < np.inf:  # as the training command's
            raise UsageError("--checkpoint-every-s must be a positive number of seconds, "
                             f"finite, got {args.checkpoint_every_s:g}")
        try:
            evaluation = EvaluationConfig(**assignments(args.eval, "--eval",
                                                         field_types(EvaluationConfig)))
        except ValueError as e:
            raise UsageError(str(e)) from None
        budget = Budget(steps=args.steps, seeds=args.seeds, evaluation=evaluation,
                        checkpoint_every=args.checkpoint_every,
                        checkpoint_every_s=args.checkpoint_every_s,
                        seeds_per_program=args.seeds_per_program,
                        overrides=tuple(assignments(args.set, "--set",
                                                     field_types(PGPSConfig)).items()),
                        env=tuple(env_assignments(args.env).items()))
        environ = dict(os.environ)
        if args.concurrent > 1:  # this process only schedules: the GPUs' memory is the cells'
            os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
        results = run(args.experiment, args.out, budget, args.tasks, args.configs,
                      progress=not args.no_progress, reference=args.reference,
                      concurrent=args.concurrent, child_environ=environ)
        for result in results:
            print(cell_summary(args.experiment, result))
        return 0

    try:
        with sigterm_as_ctrl_c():
            return report(body)
    except KeyboardInterrupt:
        print_error("interrupted; the same command continues each cell from its last "
                    "checkpoint")
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())

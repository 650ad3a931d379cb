"""The lockstep of a cell's seeds vmapped in one program, read from the cell's files.

Vmapped seeds play in lockstep: a generation's rollout lasts as long as the longest episode
among the playing seeds' actors. `generation_times.csv` records the sequential env steps of
the program's rollouts (`rollout_steps`, the most of its playing seeds'), each
`seed<k>_generations.csv` those of the seed's own rollouts, in the generations it played:
what it would have played as a program of its own. Their ratio bounds what running the seeds
as programs of their own (`--seeds-per-program 1`, each on a GPU of its own) can save in
rollout steps; the seconds per step of a seed alone are the seeds benchmark's
(`benchmarks.grid_throughput seeds`).

    python -m benchmarks.lockstep benchmarks/results/paper/table1/walker2d/pg_to_ea

Writes one entry per cell to `benchmarks/results/lockstep.json` (an entry of the same cell
is replaced) and prints a table.
"""

import argparse
import csv
import json
import pathlib
import re

from pgps_jax.cli import run_dir as rundir
from pgps_jax.experiments.paper.runner import GENERATION_TIMES

RESULTS = pathlib.Path("benchmarks/results/lockstep.json")
SEED_GENERATIONS = re.compile(r"seed(\d+)_generations\.csv")


def _rows(path: pathlib.Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def lockstep(cell: pathlib.Path) -> dict:
    """The program's sequential rollout steps against each seed's own, with the seconds the
    program's generations spent playing and learning (ValueError for a cell whose files do
    not record them: run in parts, or before `rollout_steps` was recorded)."""
    times_file = cell / GENERATION_TIMES
    if not times_file.exists():
        raise ValueError(f"{cell} has no {GENERATION_TIMES}: not a cell run whole as one "
                         "program (a cell run in parts has one per part)")
    times = _rows(times_file)
    if not times or "rollout_steps" not in times[0]:
        raise ValueError(f"{times_file} has no rollout_steps column: written before the "
                         "runner recorded it")
    seed_files = sorted((int(m.group(1)), path) for path in cell.iterdir()
                        if (m := SEED_GENERATIONS.fullmatch(path.name)))
    seeds = []
    for seed, path in seed_files:
        played = _rows(path)
        seeds.append({"seed": seed, "generations": len(played),
                      "rollout_steps": sum(int(r["rollout_steps"]) for r in played),
                      "env_steps": int(played[-1]["env_steps"]) if played else 0})
    program = sum(int(r["rollout_steps"]) for r in times)
    play = sum(float(r["play_s"]) for r in times)
    longest = max(s["rollout_steps"] for s in seeds)
    return {"cell": str(cell), "generations": len(times), "play_s": round(play, 1),
            "learn_s": round(sum(float(r["learn_s"]) for r in times), 1),
            "program_rollout_steps": program, "seeds": seeds,
            "program_over_longest_seed": round(program / longest, 3),
            "play_ms_per_program_step": round(1e3 * play / program, 3)}


def table(entries: list[dict]) -> str:
    """The entries as a markdown table."""
    lines = ["| cell | generations | play s | learn s | program's rollout steps | each seed's "
             "own | program / longest seed | play ms per program step |",
             "|---|---|---|---|---|---|---|---|"]
    for e in entries:
        own = " ".join(f"{s['rollout_steps']:,}" for s in e["seeds"])
        lines.append(f"| {e['cell']} | {e['generations']} | {e['play_s']:,.0f} | "
                     f"{e['learn_s']:,.0f} | {e['program_rollout_steps']:,} | {own} | "
                     f"{e['program_over_longest_seed']:.2f} | "
                     f"{e['play_ms_per_program_step']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cells", nargs="+", type=pathlib.Path, help="cell directories")
    parser.add_argument("--results", type=pathlib.Path, default=RESULTS)
    args = parser.parse_args()
    try:
        entries = [lockstep(cell) for cell in args.cells]
    except ValueError as error:
        raise SystemExit(f"error: {error}")
    saved = json.loads(args.results.read_text()) if args.results.exists() else []
    measured = {e["cell"] for e in entries}
    saved = [e for e in saved if e["cell"] not in measured] + entries
    args.results.parent.mkdir(parents=True, exist_ok=True)
    rundir.write_atomic(args.results, json.dumps(saved, indent=1).encode())
    print(table(entries))


if __name__ == "__main__":
    main()

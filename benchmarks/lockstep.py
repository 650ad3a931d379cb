"""The lockstep of a cell's seeds vmapped in one program, read from the cell's files.

Vmapped seeds play in lockstep: a generation's rollout lasts as long as the longest episode
among the playing seeds' actors. `generation_times.csv` records the sequential env steps of
the program's rollouts (`rollout_steps`, the most of its playing seeds'), each
`seed<k>_generations.csv` those of the seed's own rollouts, in the generations it played:
what it would have played as a program of its own. Their ratio bounds what running the seeds
as programs of their own (`--seeds-per-program 1`, each on a GPU of its own) can save in
rollout steps; the seconds per step of a seed alone are the seeds benchmark's
(`benchmarks.grid_throughput seeds`).

    python -m benchmarks.lockstep \
        benchmarks/results/cut_off_2026-11-27/table1_walker2d_one_gpu_each/base

A cell run in parts, or given more seeds, has a program per part (`--seeds-per-program`):
each is measured over its own seeds. Writes one entry per program to
`benchmarks/results/lockstep.json` (an entry of the same program is replaced) and prints a
table.
"""

import argparse
import csv
import json
import pathlib
import re

from pgps_jax.cli import run_dir as rundir
from pgps_jax.experiments.paper.runner import GENERATION_TIMES, PART, generations_file

RESULTS = pathlib.Path("benchmarks/results/lockstep.json")
_BEFORE_SEED, _, _AFTER_SEED = generations_file(0).partition("0")
SEED_GENERATIONS = re.compile(rf"{re.escape(_BEFORE_SEED)}(\d+){re.escape(_AFTER_SEED)}")
"""A seed's generations file (`runner.generations_file`), its seed captured."""
_STEM, _, _EXTENSION = GENERATION_TIMES.partition(".")
PROGRAM_TIMES = re.compile(rf"{_STEM}(?:{PART}(\d+)-(\d+))?\.{_EXTENSION}")
"""A program's times: the whole cell's, or a part's of seeds a..b (`runner.part_file`)."""


def _rows(path: pathlib.Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def programs(cell: pathlib.Path) -> list[tuple[pathlib.Path, list[int]]]:
    """Each program of `cell`: its times file and its seeds (a part's, from the file's name;
    the whole cell's program: the seeds no part holds)."""
    seeds = sorted(int(m.group(1)) for path in cell.iterdir()
                   if (m := SEED_GENERATIONS.fullmatch(path.name)))
    found = sorted(((path, m) for path in cell.iterdir()
                    if (m := PROGRAM_TIMES.fullmatch(path.name))),
                   key=lambda found: int(found[1].group(1) or 0))  # the whole cell's first
    parts = {path: list(range(int(m.group(1)), int(m.group(2)) + 1))
             for path, m in found if m.group(1)}
    in_parts = {seed for numbers in parts.values() for seed in numbers}
    return [(path, parts.get(path, [s for s in seeds if s not in in_parts]))
            for path, _ in found]


def lockstep(cell: pathlib.Path) -> list[dict]:
    """Per program of `cell` (`programs`): its sequential rollout steps against each of its
    seeds' own, with the seconds its generations spent playing and learning (ValueError for
    a cell whose files do not record them: no times file, or one written before
    `rollout_steps` was recorded)."""
    if not cell.is_dir():
        raise ValueError(f"{cell} is not a directory: give a cell's folder, "
                         "<out>/<experiment>/<task>/<config>")
    found = programs(cell)
    if not found:
        raise ValueError(f"{cell} has no {GENERATION_TIMES} (nor a part's): not a cell, or "
                         "one run before the runner recorded its generations' times")
    return [_program(cell, times_file, seeds) for times_file, seeds in found]


def _program(cell: pathlib.Path, times_file: pathlib.Path, numbers: list[int]) -> dict:
    times = _rows(times_file)
    if not times or "rollout_steps" not in times[0]:
        raise ValueError(f"{times_file} has no rollout_steps column: written before the "
                         "runner recorded it")
    files = {seed: cell / generations_file(seed) for seed in numbers}
    missing = [path.name for path in files.values() if not path.exists()]
    if not files or missing:
        raise ValueError(f"{cell}: the seeds' generations files of {times_file.name} are "
                         f"missing ({', '.join(missing) or 'no seed has one'})")
    seeds = []
    for seed, path in files.items():
        played = _rows(path)
        seeds.append({"seed": seed, "generations": len(played),
                      "rollout_steps": sum(int(r["rollout_steps"]) for r in played),
                      "env_steps": int(played[-1]["env_steps"]) if played else 0})
    program = sum(int(r["rollout_steps"]) for r in times)
    play = sum(float(r["play_s"]) for r in times)
    longest = max(s["rollout_steps"] for s in seeds)
    return {"cell": str(cell), "program": times_file.name, "generations": len(times),
            "play_s": round(play, 1),
            "learn_s": round(sum(float(r["learn_s"]) for r in times), 1),
            "program_rollout_steps": program, "seeds": seeds,
            "program_over_longest_seed": round(program / longest, 3),
            "play_ms_per_program_step": round(1e3 * play / program, 3)}


def table(entries: list[dict]) -> str:
    """The entries as a markdown table."""
    lines = ["| cell | program | generations | play s | learn s | program's rollout steps "
             "| each seed's own | program / longest seed | play ms per program step |",
             "|---|---|---|---|---|---|---|---|---|"]
    for e in entries:
        own = " ".join(f"{s['rollout_steps']:,}" for s in e["seeds"])
        lines.append(f"| {e['cell']} | {e['program']} | {e['generations']} | "
                     f"{e['play_s']:,.0f} | {e['learn_s']:,.0f} | "
                     f"{e['program_rollout_steps']:,} | {own} | "
                     f"{e['program_over_longest_seed']:.2f} | "
                     f"{e['play_ms_per_program_step']:.2f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cells", nargs="+", type=pathlib.Path, help="cell directories")
    parser.add_argument("--results", type=pathlib.Path, default=RESULTS)
    args = parser.parse_args()
    try:
        entries = [entry for cell in args.cells for entry in lockstep(cell)]
    except ValueError as error:
        raise SystemExit(f"error: {error}")
    saved = json.loads(args.results.read_text()) if args.results.exists() else []
    measured = {(e["cell"], e["program"]) for e in entries}
    saved = [e for e in saved if (e["cell"], e.get("program")) not in measured] + entries
    args.results.parent.mkdir(parents=True, exist_ok=True)
    rundir.write_atomic(args.results, json.dumps(saved, indent=1).encode())
    print(table(entries))


if __name__ == "__main__":
    main()

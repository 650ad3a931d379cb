"""Where μ's test return swings, read from a finished cell's files: per seed, the mean and
the lowest of μ's evaluations late in the run, and how μ's evaluation changes across the
generations in which the TD3 actor ranked among the CEM's top K, ranked below them, or did not
play (the CEM's μ is the weighted mean of the top K; Section 3, Figure 2b).

An evaluation starts at a generation's end and plays μ as that generation's CEM update left
it, so between two evaluations lie the updates of the generations ending after the first and
up to the second: one on the swimmer and halfcheetah (a generation of 10k steps), one to four
on hopper. Each such interval is classed by the TD3 actor's highest rank in its generations
(in the top K in any of them; else below it in any; else not played) and counts once. Σ's
growth is classed per generation. Given `--against`, each cell's late means are compared
with those of the same task's cell there by the two-sided Mann–Whitney test, exact over every
split of the pooled seeds.

    python -m benchmarks.mu_swings \
        benchmarks/results/paper_defaults/figure4/{swimmer,halfcheetah,hopper}/pgps \
        --against benchmarks/results/paper/figure4

Writes `benchmarks/results/mu_swings.json` (keyed by cell folder) and prints one table.
"""

import argparse
import csv
import itertools
import math
import pathlib
from typing import Optional

import numpy as np

from benchmarks.finished_cell import measure_cells, pgps_result
from pgps_jax.experiments.paper.report import read_curve, seeds_in
from pgps_jax.experiments.paper.runner import generations_file, seed_file

OUT = pathlib.Path("benchmarks/results/mu_swings.json")
CLASSES = ("td3_in_top_k", "td3_below_top_k", "td3_not_played")
EXACT_SPLITS = 1_000_000
"""The most splits of the pooled seeds the Mann–Whitney test enumerates."""


def late_evaluations(cell: pathlib.Path, start: float) -> dict[int, dict[str, float]]:
    """Per seed, the mean and the lowest of μ's evaluations at env steps ≥ `start`."""
    late = {}
    for seed in seeds_in(cell):
        steps, returns = read_curve(cell / seed_file(seed))
        chosen = returns[steps >= start]
        if chosen.size:
            late[seed] = {"mean": float(chosen.mean()), "lowest": float(chosen.min())}
    return late


def td3_class(row: dict, top_k: int) -> str:
    """Where the TD3 actor ranked in a generation (`CLASSES`), ranking ties as the CEM's
    stable sort does: the lower slot first. The TD3 actor's slot is the last whose return is
    its return."""
    if not float(row["td3_in_population"]):
        return CLASSES[2]
    returns = np.array([float(v) for k, v in row.items() if k.startswith("return_")])
    slots = np.flatnonzero(returns == float(row["td3_return"]))
    if slots.size == 0:
        raise ValueError(f"generation {row.get('generation')}: no slot's return is the TD3 "
                         f"actor's {row['td3_return']}")
    rank = int(np.flatnonzero(np.argsort(-returns, kind="stable") == slots[-1])[0])
    return CLASSES[0] if rank < top_k else CLASSES[1]


def interval_changes(generations: list[dict], steps: np.ndarray, returns: np.ndarray,
                     top_k: int, after: float) -> list[tuple[str, float]]:
    """(class, change of μ's evaluation) for each pair of consecutive evaluations from
    `after` env steps on with at least one generation ending between them (after the first,
    up to and including the second)."""
    ends = np.array([float(row["env_steps"]) for row in generations])
    changes = []
    for i in range(1, len(steps)):
        if steps[i - 1] < after:
            continue
        between = [td3_class(generations[j], top_k)
                   for j in np.flatnonzero((ends > steps[i - 1]) & (ends <= steps[i]))]
        if between:
            kind = next(k for k in CLASSES if k in between)
            changes.append((kind, float(returns[i] - returns[i - 1])))
    return changes


def generation_var_ratios(generations: list[dict], top_k: int, after: float
                          ) -> list[tuple[str, float]]:
    """(class, Σ's mean over the generation before's) for each generation ending after
    `after` env steps."""
    return [(td3_class(row, top_k), float(row["cem_var_mean"]) / float(previous["cem_var_mean"]))
            for previous, row in zip(generations, generations[1:])
            if float(row["env_steps"]) > after]


def rank_effect(cell: pathlib.Path, top_k: int, after: float, fall: float) -> dict:
    """Per class (CLASSES), over the cell's seeds: the intervals between μ's evaluations
    (`interval_changes`), the mean change of μ's evaluation across them and the share in
    which it fell by more than `fall`; the generations (`generation_var_ratios`) and their
    median ratio of Σ's mean to the generation before's."""
    changes, ratios = [], []
    for seed in seeds_in(cell):
        with open(cell / generations_file(seed), newline="") as f:
            generations = list(csv.DictReader(f))
        changes += interval_changes(generations, *read_curve(cell / seed_file(seed)),
                                    top_k, after)
        ratios += generation_var_ratios(generations, top_k, after)
    summary = {}
    for kind in CLASSES:
        change = np.array([c for k, c in changes if k == kind])
        ratio = np.array([r for k, r in ratios if k == kind])
        summary[kind] = {"intervals": int(change.size),
                         "mean_change": float(change.mean()) if change.size else None,
                         "fall_share": float(np.mean(change < -fall)) if change.size else None,
                         "generations": int(ratio.size),
                         "median_var_ratio": float(np.median(ratio)) if ratio.size else None}
    return summary


def mann_whitney_p(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sided exact p of the Mann–Whitney U test: the share of the splits of the pooled
    values into groups of len(a) and len(b) whose U is at least as far out in either tail
    (ties take mid-ranks), twice the smaller tail, at most 1."""
    pooled = np.concatenate([a, b])
    splits = math.comb(len(pooled), len(a))
    if splits > EXACT_SPLITS:
        raise ValueError(f"{len(a)} against {len(b)} values make {splits:,} splits, more than "
                         f"the {EXACT_SPLITS:,} this exact test enumerates")
    order = pooled.argsort(kind="stable")
    ranks = np.empty(len(pooled))
    ranks[order] = np.arange(1, len(pooled) + 1)
    for value in np.unique(pooled):  # mid-ranks for ties
        ranks[pooled == value] = ranks[pooled == value].mean()
    offset = len(a) * (len(a) + 1) / 2
    observed = ranks[:len(a)].sum() - offset
    us = np.array([ranks[list(chosen)].sum() - offset
                   for chosen in itertools.combinations(range(len(pooled)), len(a))])
    low, high = np.mean(us <= observed + 1e-9), np.mean(us >= observed - 1e-9)
    return float(min(1.0, 2 * min(low, high)))


def top_k_of(cell: pathlib.Path) -> int:
    """K of the configuration the cell ran (`finished_cell.pgps_result`); ValueError for a
    cell whose TD3 actor plays outside the population (EA→PG without PG→EA: its probe
    slot)."""
    result = pgps_result(cell, "pg_guides_ea", "the TD3 actor does not join the population "
                         "and its rank among the CEM's actors means nothing")
    return int(result["settings"]["config"]["top_k"])


def measure(cell: pathlib.Path, against: Optional[pathlib.Path], late_from: float,
            after: float, fall: float) -> dict:
    """One cell's late evaluations and rank effect, and, where `against` is given and holds
    another folder for the cell's task and configuration, the comparison with it."""
    late = late_evaluations(cell, late_from)
    entry = {"late_from": late_from, "late": late,
             "rank_effect": {"after": after, "fall": fall,
                             **rank_effect(cell, top_k_of(cell), after, fall)}}
    if against is not None:
        other = against / cell.parent.name / cell.name
        if other.resolve() == cell.resolve():
            return entry
        top_k_of(other)  # the checks the cell passed: a finished PGPS cell
        other_late = late_evaluations(other, late_from)
        if not late or not other_late:
            raise ValueError(f"{cell if not late else other} has no evaluation from "
                             f"{late_from:,.0f} env steps on to compare")
        ours = np.array([v["mean"] for v in late.values()])
        theirs = np.array([v["mean"] for v in other_late.values()])
        entry["against"] = {"cell": str(other), "late": other_late,
                            "mann_whitney_p": mann_whitney_p(ours, theirs)}
    return entry


def table(results: dict) -> str:
    """The measurements as a markdown table, one row per cell; the columns of the classes
    read td3_in_top_k / td3_below_top_k / td3_not_played."""
    lines = ["| cell | late μ per seed (mean) | against (mean) | p | intervals "
             "| mean change of μ | falls | generations | Σ ratio |",
             "|---|---|---|---|---|---|---|---|---|"]
    for cell, entry in results.items():
        late = [v["mean"] for v in entry["late"].values()]
        other = entry.get("against")
        effect = [entry["rank_effect"][k] for k in CLASSES]

        def each(field, form):
            return " / ".join("–" if e[field] is None else format(e[field], form)
                              for e in effect)

        compared = "– | –"
        if other:
            other_mean = np.mean([v["mean"] for v in other["late"].values()])
            compared = f"{other_mean:,.0f} | {other['mann_whitney_p']:.3f}"
        lines.append(
            f"| {cell} | {' '.join(f'{x:,.0f}' for x in late)} ({np.mean(late):,.0f}) | "
            f"{compared} | {each('intervals', 'd')} | {each('mean_change', '+,.0f')} | "
            f"{each('fall_share', '.0%')} | {each('generations', 'd')} | "
            f"{each('median_var_ratio', '.2f')} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cells", nargs="+", type=pathlib.Path,
                        help="cell folders (<experiment>/<task>/<config>) of finished runs")
    parser.add_argument("--against", type=pathlib.Path, default=None,
                        help="an experiment folder holding the same tasks' cells to compare with")
    parser.add_argument("--late-from", type=float, default=800_000,
                        help="μ's evaluations from this env step on are the late ones")
    parser.add_argument("--after", type=float, default=300_000,
                        help="intervals and generations from this env step on are classed")
    parser.add_argument("--fall", type=float, default=100.0,
                        help="a change of μ's evaluation below minus this is a fall")
    parser.add_argument("--out", type=pathlib.Path, default=OUT)
    args = parser.parse_args()
    measure_cells(parser, args.cells,
                  lambda cell: measure(cell, args.against, args.late_from, args.after, args.fall),
                  table, args.out)


if __name__ == "__main__":
    main()

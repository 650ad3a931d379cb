"""Where μ's test return swings, read from a finished cell's files: per seed, the mean and
the lowest of μ's evaluations late in the run, and how μ's evaluation changes across a
generation in which the TD3 actor ranked among the CEM's top K, ranked below them, or did not
play (the CEM's μ is the weighted mean of the top K; Section 3, Figure 2b).

A generation ending at env step e is paired with μ's last evaluation before e and its first
at or after e (the test episodes ride along the rollouts, so the first played μ before this
generation's CEM update and the second after it). Given `--against`, each cell's late means
are compared with those of the same task's cell there by the two-sided Mann–Whitney test,
exact over every split of the pooled seeds.

    python -m benchmarks.mu_swings benchmarks/results/paper_defaults/figure4/{swimmer,halfcheetah,hopper}/pgps \
        --against benchmarks/results/paper/figure4

Writes `benchmarks/results/mu_swings.json` (keyed by cell folder) and prints one table.
"""

import argparse
import csv
import itertools
import json
import math
import pathlib
from typing import Optional

import numpy as np

from pgps_jax.experiments.paper.report import read_curve
from pgps_jax.experiments.paper.runner import generations_file, seed_file

OUT = pathlib.Path("benchmarks/results/mu_swings.json")
CLASSES = ("td3_in_top_k", "td3_below_top_k", "td3_not_played")
EXACT_SPLITS = 1_000_000
"""The most splits of the pooled seeds the Mann–Whitney test enumerates."""


def seeds_of(cell: pathlib.Path) -> list[int]:
    """The seeds whose μ curve the cell holds, in order."""
    return sorted(int(p.stem[4:]) for p in cell.glob("seed*.csv") if p.stem[4:].isdigit())


def late_evaluations(cell: pathlib.Path, start: float) -> dict[int, dict[str, float]]:
    """Per seed, the mean and the lowest of μ's evaluations at env steps ≥ `start`."""
    late = {}
    for seed in seeds_of(cell):
        steps, returns = read_curve(cell / seed_file(seed))
        chosen = returns[steps >= start]
        if chosen.size:
            late[seed] = {"mean": float(chosen.mean()), "lowest": float(chosen.min())}
    return late


def generation_changes(generations: list[dict], steps: np.ndarray, returns: np.ndarray,
                       top_k: int, after: float) -> list[tuple[str, float, float]]:
    """(class, change of μ's evaluation, Σ's mean over the generation before's) for each
    generation ending after `after` env steps with μ evaluated on both sides of its end."""
    changes = []
    for previous, row in zip(generations, generations[1:]):
        end = float(row["env_steps"])
        following = int(np.searchsorted(steps, end))
        if end <= after or following == 0 or following == len(steps):
            continue
        if float(row["td3_in_population"]):
            td3 = float(row["td3_return"])
            above = sum(float(v) > td3 for k, v in row.items() if k.startswith("return_"))
            kind = CLASSES[0] if above < top_k else CLASSES[1]
        else:
            kind = CLASSES[2]
        changes.append((kind, float(returns[following] - returns[following - 1]),
                        float(row["cem_var_mean"]) / float(previous["cem_var_mean"])))
    return changes


def rank_effect(cell: pathlib.Path, top_k: int, after: float, fall: float) -> dict:
    """Per class of generation (CLASSES), over the cell's seeds: how many, the mean change of
    μ's evaluation across them, the share in which it fell by more than `fall`, and the
    median ratio of Σ's mean to the generation before's."""
    changes = []
    for seed in seeds_of(cell):
        with open(cell / generations_file(seed), newline="") as f:
            generations = list(csv.DictReader(f))
        changes += generation_changes(generations, *read_curve(cell / seed_file(seed)),
                                      top_k, after)
    summary = {}
    for kind in CLASSES:
        change = np.array([c for k, c, _ in changes if k == kind])
        ratio = np.array([r for k, _, r in changes if k == kind])
        summary[kind] = {"generations": int(change.size),
                         "mean_change": float(change.mean()) if change.size else None,
                         "fall_share": float(np.mean(change < -fall)) if change.size else None,
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
    """K of the configuration the cell ran (its `result.json`)."""
    result = json.loads((cell / "result.json").read_text())
    return int(result["settings"]["config"]["top_k"])


def measure(cell: pathlib.Path, against: Optional[pathlib.Path], late_from: float,
            after: float, fall: float) -> dict:
    """One cell's late evaluations and rank effect, and its comparison with `against`'s
    cell of the same task and configuration where given."""
    late = late_evaluations(cell, late_from)
    entry = {"late_from": late_from, "late": late,
             "rank_effect": {"after": after, "fall": fall,
                             **rank_effect(cell, top_k_of(cell), after, fall)}}
    if against is not None:
        other = against / cell.parent.name / cell.name
        other_late = late_evaluations(other, late_from)
        ours = np.array([v["mean"] for v in late.values()])
        theirs = np.array([v["mean"] for v in other_late.values()])
        entry["against"] = {"cell": str(other), "late": other_late,
                            "mann_whitney_p": mann_whitney_p(ours, theirs)}
    return entry


def table(results: dict) -> str:
    """The measurements as a markdown table, one row per cell."""
    lines = ["| cell | late μ per seed (mean) | against (mean) | p | generations: "
             + ", ".join(CLASSES) + " | mean change of μ | falls | Σ ratio |",
             "|---|---|---|---|---|---|---|---|"]
    for cell, entry in results.items():
        late = [v["mean"] for v in entry["late"].values()]
        other = entry.get("against", {})
        other_means = [v["mean"] for v in other.get("late", {}).values()]
        effect = [entry["rank_effect"][k] for k in CLASSES]

        def each(field, form):
            return " / ".join("–" if e[field] is None else format(e[field], form) for e in effect)

        lines.append(
            f"| {cell} | {' '.join(f'{x:,.0f}' for x in late)} ({np.mean(late):,.0f}) | "
            + (f"{np.mean(other_means):,.0f} | {other['mann_whitney_p']:.3f}" if other else "– | –")
            + f" | {each('generations', 'd')} | {each('mean_change', '+,.0f')} | "
            f"{each('fall_share', '.0%')} | {each('median_var_ratio', '.2f')} |")
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
                        help="generations ending after this env step are classed")
    parser.add_argument("--fall", type=float, default=100.0,
                        help="a change of μ's evaluation below minus this is a fall")
    parser.add_argument("--out", type=pathlib.Path, default=OUT)
    args = parser.parse_args()
    for cell in args.cells:
        if not (cell / "result.json").exists():
            parser.error(f"{cell} holds no result.json: not a finished cell's folder")
    results = {str(cell): measure(cell, args.against, args.late_from, args.after, args.fall)
               for cell in args.cells}
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(table(results))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

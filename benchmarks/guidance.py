"""How EA→PG pulled the TD3 actor, read from a finished PGPS cell's files: per seed, in the
generations before Q-filtering starts and in those after (up to `--until` env steps), the
share whose elite fell at once (scored below `--fallen`), whose β ended at its upper bound
(eq. 3) and in which the TD3 actor was guided (it fell behind, Algorithm 1); of those in
which the TD3 actor played in the population (PG→EA), the share in which it fell at once and
the share in which it was the elite; the median of the TD3 actor's test returns from
`--late-from` env steps on, μ's evaluation nearest `--at` env steps, and μ's final return.

    python -m benchmarks.guidance \
        benchmarks/results/authors_code/figure4/walker2d/pgps \
        benchmarks/results/walker2d_beta_after_block_200k/figure4/walker2d/pgps

Writes `benchmarks/results/guidance.json` (keyed by cell folder) and prints one table.
"""

import argparse
import csv
import pathlib
from typing import Optional

import numpy as np

from benchmarks.finished_cell import measure_cells, pgps_result
from pgps_jax.experiments.paper.report import read_curve, seeds_in
from pgps_jax.experiments.paper.runner import generations_file, seed_file

OUT = pathlib.Path("benchmarks/results/guidance.json")
PHASES = ("before_q_filter", "after_q_filter")


def cell_config(cell: pathlib.Path) -> dict:
    """The PGPSConfig the cell ran and μ's final return per seed
    (`finished_cell.pgps_result`); ValueError for a cell whose TD3 actor is never guided."""
    result = pgps_result(cell, "ea_guides_pg", "nothing guides the TD3 actor")
    return {"config": result["settings"]["config"],
            "final": dict(zip(result["seeds"], result["final"]["mu"]))}


def phase_shares(generations: list[dict], beta_max: float, fallen: float) -> dict:
    """Per phase (`PHASES`, by each generation's `q_filter_active`): the generations, and the
    shares whose elite scored below `fallen`, whose β ended at `beta_max` and that guided the
    TD3 actor; of the generations in which the TD3 actor played, the shares in which it scored
    below `fallen` and in which it was the elite (None where there are no such generations)."""
    def share(rows, test):
        return float(np.mean([test(r) for r in rows])) if rows else None

    shares = {}
    for phase, active in zip(PHASES, (False, True)):
        rows = [r for r in generations if bool(float(r["q_filter_active"])) == active]
        played = [r for r in rows if bool(float(r["td3_in_population"]))]
        shares[phase] = {
            "generations": len(rows),
            "elite_fallen": share(rows, lambda r: float(r["elite_return"]) < fallen),
            "beta_at_bound": share(rows, lambda r: float(r["beta"]) >= beta_max),
            "guided": share(rows, lambda r: float(r["guided_loss"]) != 0.0),
            "td3_fallen": share(played, lambda r: float(r["td3_return"]) < fallen),
            "td3_elite": share(played,
                               lambda r: float(r["td3_return"]) == float(r["elite_return"]))}
    return shares


def nearest_evaluation(steps: np.ndarray, returns: np.ndarray, at: float) -> dict:
    """The evaluation whose env steps lie nearest `at` (the earlier of two as near)."""
    i = int(np.argmin(np.abs(steps - at)))
    return {"env_steps": float(steps[i]), "return": float(returns[i])}


def measure(cell: pathlib.Path, fallen: float, late_from: float, at: float,
            until: Optional[float] = None) -> dict:
    """Per seed of the cell: `phase_shares` of its generations up to `until` env steps (all
    without it), the TD3 actor's median test return from `late_from` on (None without such an
    evaluation), μ's evaluation nearest `at`, and μ's final return."""
    ran = cell_config(cell)
    seeds = {}
    for seed in seeds_in(cell):
        with open(cell / generations_file(seed), newline="") as f:
            generations = [row for row in csv.DictReader(f)
                           if until is None or float(row["env_steps"]) <= until]
        td3_steps, td3_returns = read_curve(cell / seed_file(seed, "td3"))
        late = td3_returns[td3_steps >= late_from]
        seeds[seed] = {**phase_shares(generations, ran["config"]["beta_max"], fallen),
                       "td3_late_median": float(np.median(late)) if late.size else None,
                       "mu_near": nearest_evaluation(*read_curve(cell / seed_file(seed)), at),
                       "final_mu": ran["final"].get(seed)}
    return {"fallen": fallen, "late_from": late_from, "at": at, "until": until, "seeds": seeds}


def table(results: dict) -> str:
    """The measurements as a markdown table, one row per seed."""

    def percent(value):
        return "–" if value is None else f"{value:.0%}"

    def number(value):
        return "–" if value is None else f"{value:,.0f}"

    lines = ["| cell | seed | generations before / after Q-filtering | elite fallen, before "
             "| β at bound, before / after | guided, before / after | TD3 actor fallen, before "
             "| TD3 actor the elite, before | TD3 late median | μ near `at` | final μ |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for cell, entry in results.items():
        for seed, s in entry["seeds"].items():
            before, after = s[PHASES[0]], s[PHASES[1]]
            lines.append(
                f"| {cell} | {seed} | {before['generations']} / {after['generations']} "
                f"| {percent(before['elite_fallen'])} "
                f"| {percent(before['beta_at_bound'])} / {percent(after['beta_at_bound'])} "
                f"| {percent(before['guided'])} / {percent(after['guided'])} "
                f"| {percent(before['td3_fallen'])} | {percent(before['td3_elite'])} "
                f"| {number(s['td3_late_median'])} | {number(s['mu_near']['return'])} "
                f"| {number(s['final_mu'])} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cells", nargs="+", type=pathlib.Path,
                        help="finished PGPS cells' folders (<out>/<experiment>/<task>/<config>)")
    parser.add_argument("--fallen", type=float, default=50.0,
                        help="an elite or TD3 actor scoring below this fell at once (default 50)")
    parser.add_argument("--late-from", type=float, default=500_000.0,
                        help="env steps from which the TD3 actor's returns count as late")
    parser.add_argument("--at", type=float, default=200_000.0,
                        help="env steps near which μ's evaluation is reported")
    parser.add_argument("--until", type=float, default=None,
                        help="count only the generations that end at or before these env steps")
    parser.add_argument("--out", type=pathlib.Path, default=OUT)
    args = parser.parse_args(argv)
    return measure_cells(parser, args.cells,
                         lambda cell: measure(cell, args.fallen, args.late_from, args.at,
                                              args.until),
                         table, args.out)


if __name__ == "__main__":
    main()

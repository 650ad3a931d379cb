"""benchmarks.mu_swings: the exact Mann–Whitney test against scipy's, the TD3 actor's rank as
the CEM's stable sort gives it, and the intervals between μ's evaluations on hand-made
cells."""

import csv
import json

import numpy as np
import pytest
from scipy import stats

from benchmarks import mu_swings


@pytest.mark.parametrize("sizes", [(5, 10), (3, 4), (6, 6)])
def test_mann_whitney_p_equals_scipys_exact_test(sizes):
    rng = np.random.default_rng(sum(sizes))
    a, b = rng.normal(0.0, 1.0, sizes[0]), rng.normal(0.8, 1.0, sizes[1])
    expected = stats.mannwhitneyu(a, b, alternative="two-sided", method="exact").pvalue
    assert mu_swings.mann_whitney_p(a, b) == pytest.approx(expected, rel=1e-9)


def test_mann_whitney_p_gives_tied_values_their_mid_ranks():
    # Pooled 1, 2, 2, 3 rank 1, 2.5, 2.5, 4: the six splits' U are 0.5, 0.5, 2, 2, 3.5, 3.5,
    # so U = 0.5 is in the lower tail with probability 2/6, and p = 2 · 2/6.
    assert mu_swings.mann_whitney_p(np.array([1.0, 2.0]), np.array([2.0, 3.0])) == \
        pytest.approx(2 / 3)


def test_mann_whitney_p_refuses_more_splits_than_it_enumerates():
    with pytest.raises(ValueError, match="splits"):
        mu_swings.mann_whitney_p(np.zeros(20), np.ones(20))


def _row(steps, returns, td3, var):
    row = {"generation": steps // 100, "env_steps": steps,
           "td3_in_population": int(td3 is not None),
           "td3_return": "nan" if td3 is None else td3, "cem_var_mean": var}
    row.update({f"return_{i}": r for i, r in enumerate(returns)})
    return row


@pytest.mark.parametrize("returns, td3, top_k, expected", [
    ([9, 8, 7, 1], 8, 2, "td3_in_top_k"),       # second of four
    ([9, 8, 7, 1], 7, 2, "td3_below_top_k"),    # third: the first below the top 2
    ([9, 8, 7, 1], 7, 3, "td3_in_top_k"),
    ([9, 5, 1, 5], 5, 2, "td3_below_top_k"),    # tied with slot 1, the TD3 actor's slot 3 after it
    ([9, 5, 1, 5], 5, 3, "td3_in_top_k"),
    ([9, 5, 1, 5], None, 2, "td3_not_played"),
])
def test_the_td3_actors_rank_is_the_cems_stable_sort(returns, td3, top_k, expected):
    assert mu_swings.td3_class(_row(100, returns, td3, 1.0), top_k) == expected


def test_a_td3_return_no_slot_holds_is_refused():
    with pytest.raises(ValueError, match="no slot's return"):
        mu_swings.td3_class(_row(100, [9, 8, 7, 1], 6, 1.0), 2)


# Generations end at 100, 200, ..., 600; μ is evaluated at 100, 300, 400, 600 and 700, each
# time as the generation ending there left it.
GENERATIONS = [
    _row(100, [5, 4, 3, 2], None, 1.0),
    _row(200, [9, 8, 7, 1], 1, 2.0),      # below the top 2 ...
    _row(300, [9, 8, 7, 1], 8, 4.0),      # ... then in it: the interval (100, 300] is top K
    _row(400, [6, 5, 4, 3], 3, 1.0),      # (300, 400]: below the top 2
    _row(500, [6, 5, 4, 3], None, 0.5),
    _row(600, [6, 5, 4, 3], None, 0.5),   # (400, 600]: not played
]
CURVE = (np.array([100.0, 300.0, 400.0, 600.0, 700.0]),
         np.array([10.0, -190.0, -170.0, -160.0, 0.0]))


def test_each_interval_between_evaluations_counts_once_by_its_highest_class():
    changes = mu_swings.interval_changes(GENERATIONS, *CURVE, top_k=2, after=100)
    # (600, 700] holds no generation's end: no update lies between those evaluations
    assert changes == [("td3_in_top_k", -200.0), ("td3_below_top_k", 20.0),
                       ("td3_not_played", 10.0)]
    assert mu_swings.interval_changes(GENERATIONS, *CURVE, top_k=2, after=300) == changes[1:]


def test_sigmas_growth_is_classed_per_generation():
    assert mu_swings.generation_var_ratios(GENERATIONS, top_k=2, after=300) == [
        ("td3_below_top_k", 0.25), ("td3_not_played", 0.5), ("td3_not_played", 1.0)]


def _write_cell(folder, shift=0.0, pg_guides_ea=True, algo="pgps"):
    folder.mkdir(parents=True)
    config = {"top_k": 2, "pg_guides_ea": pg_guides_ea}
    (folder / "result.json").write_text(json.dumps({"algo": algo,
                                                    "settings": {"config": config}}))
    for seed in (1, 2):
        with open(folder / f"seed{seed}.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["", "Step", "Mean"])
            writer.writerows([i, s, r + shift + seed] for i, (s, r) in enumerate(zip(*CURVE)))
        with open(folder / f"seed{seed}_generations.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(GENERATIONS[0]))
            writer.writeheader()
            writer.writerows(GENERATIONS)


def test_measure_compares_a_cell_with_the_same_tasks_cell_elsewhere(tmp_path):
    cell = tmp_path / "figure4" / "hopper" / "pgps"
    _write_cell(cell)
    _write_cell(tmp_path / "other" / "hopper" / "pgps", shift=1000.0)
    entry = mu_swings.measure(cell, tmp_path / "other", late_from=400, after=100, fall=100)
    assert entry["late"] == {1: {"mean": -109.0, "lowest": -169.0},
                             2: {"mean": -108.0, "lowest": -168.0}}
    assert entry["rank_effect"]["td3_in_top_k"] == {
        "intervals": 2, "mean_change": -200.0, "fall_share": 1.0,
        "generations": 2, "median_var_ratio": 2.0}
    # both of ours below both of theirs: U = 0, the lowest of the six splits' U
    assert entry["against"]["mann_whitney_p"] == pytest.approx(2 / 6)
    assert "| -109 -108 (-108) | 892 | 0.333 | 2 / 2 / 2 |" in mu_swings.table({"c": entry})
    # a cell is not compared with itself
    assert "against" not in mu_swings.measure(cell, tmp_path / "figure4", 400, 100, 100)


def test_measure_refuses_a_missing_cell_another_algorithm_and_a_td3_actor_outside(tmp_path):
    cell = tmp_path / "figure4" / "hopper" / "pgps"
    _write_cell(cell)
    with pytest.raises(ValueError, match="no result.json"):
        mu_swings.measure(cell, tmp_path / "nowhere", 400, 100, 100)
    probe = tmp_path / "probe" / "hopper" / "pgps"
    _write_cell(probe, pg_guides_ea=False)
    with pytest.raises(ValueError, match="pg_guides_ea"):
        mu_swings.measure(probe, None, 400, 100, 100)
    cem = tmp_path / "cem" / "hopper" / "cem"
    _write_cell(cem, algo="cem")
    with pytest.raises(ValueError, match="a cell of cem"):
        mu_swings.measure(cem, None, 400, 100, 100)

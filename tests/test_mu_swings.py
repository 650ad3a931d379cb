"""benchmarks.mu_swings: the exact Mann–Whitney test against scipy's, and the classes of
generations by the TD3 actor's rank on a hand-made cell."""

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
    row = {"env_steps": steps, "td3_in_population": int(td3 is not None),
           "td3_return": "nan" if td3 is None else td3, "cem_var_mean": var}
    row.update({f"return_{i}": r for i, r in enumerate(returns)})
    return row


GENERATIONS = [
    _row(100, [5, 4, 3, 2], None, 1.0),   # before `after`: left out
    _row(200, [9, 8, 7, 1], 8, 2.0),      # TD3 second of four: in the top 2
    _row(300, [9, 8, 7, 1], 1, 1.0),      # TD3 last: below the top 2
    _row(400, [6, 5, 4, 3], None, 0.5),   # TD3 did not play
    _row(500, [6, 5, 4, 3], None, 0.5),   # no evaluation after it: left out
]
CURVE = (np.array([150.0, 250.0, 350.0, 450.0]), np.array([10.0, -190.0, -170.0, -160.0]))


def test_generations_are_classed_by_the_td3_actors_rank():
    changes = mu_swings.generation_changes(GENERATIONS, *CURVE, top_k=2, after=150)
    assert changes == [("td3_in_top_k", -200.0, 2.0), ("td3_below_top_k", 20.0, 0.5),
                       ("td3_not_played", 10.0, 0.5)]


def test_measure_reads_a_cells_files(tmp_path):
    cell = tmp_path / "figure4" / "hopper" / "pgps"
    for folder, shift in ((cell, 0.0), (tmp_path / "other" / "hopper" / "pgps", 1000.0)):
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps({"settings": {"config": {"top_k": 2}}}))
        with open(folder / "seed1.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["", "Step", "Mean"])
            writer.writerows([i, s, r + shift] for i, (s, r) in enumerate(zip(*CURVE)))
        with open(folder / "seed1_generations.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(GENERATIONS[0]))
            writer.writeheader()
            writer.writerows(GENERATIONS)
    entry = mu_swings.measure(cell, tmp_path / "other", late_from=300, after=150, fall=100)
    assert entry["late"] == {1: {"mean": -165.0, "lowest": -170.0}}
    assert entry["rank_effect"]["td3_in_top_k"] == {
        "generations": 1, "mean_change": -200.0, "fall_share": 1.0, "median_var_ratio": 2.0}
    assert entry["against"]["late"] == {1: {"mean": 835.0, "lowest": 830.0}}
    assert entry["against"]["mann_whitney_p"] == pytest.approx(1.0)
    assert "| -165 (-165) | 835 |" in mu_swings.table({"cell": entry})

"""benchmarks.guidance on a hand-made cell: the shares of each phase, the late median of the
TD3 actor, μ's evaluation nearest a step, and the cells it refuses."""

import csv
import json

import pytest

from benchmarks import guidance


def _row(steps, q_filter, elite, beta, guided, td3=None):
    return {"generation": steps // 100, "env_steps": steps, "q_filter_active": int(q_filter),
            "elite_return": elite, "beta": beta, "guided_loss": 0.5 if guided else 0.0,
            "td3_in_population": int(td3 is not None), "td3_return": 0.0 if td3 is None else td3}


# Four generations before Q-filtering starts, two after; β's bound is 8. The TD3 actor plays
# in three of the four before (falling in two, the elite in one) and in one after.
GENERATIONS = [
    _row(100, False, -3.0, 8.0, True, td3=-7.0),   # fallen elite, β at bound, guided; TD3 fell
    _row(200, False, 12.0, 8.0, True),             # fallen elite (below 50), β at bound
    _row(300, False, 400.0, 4.0, False, td3=400.0),  # the TD3 actor is the elite
    _row(400, False, 49.9, 8.0, False, td3=20.0),  # fallen elite, β at bound; TD3 fell
    _row(500, True, 900.0, 8.0, True, td3=600.0),  # β at bound, guided
    _row(600, True, 950.0, 2.0, False),
]


def _curve(folder, name, points):
    with open(folder / name, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["", "Step", "Mean"])
        writer.writerows([i, s, r] for i, (s, r) in enumerate(points))


def _write_cell(folder, algo="pgps", ea_guides_pg=True):
    folder.mkdir(parents=True)
    config = {"beta_max": 8.0, "ea_guides_pg": ea_guides_pg}
    (folder / "result.json").write_text(json.dumps({
        "algo": algo, "seeds": [1], "final": {"mu": [1234.0]},
        "settings": {"config": config}}))
    with open(folder / "seed1_generations.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(GENERATIONS[0]))
        writer.writeheader()
        writer.writerows(GENERATIONS)
    _curve(folder, "seed1.csv", [(100, 10.0), (250, 20.0), (350, 30.0), (600, 40.0)])
    _curve(folder, "seed1_td3.csv", [(100, 1.0), (300, 7.0), (400, 3.0), (600, 5.0)])


def test_measure_gives_each_phases_shares_and_the_seeds_returns(tmp_path):
    cell = tmp_path / "figure4" / "walker2d" / "pgps"
    _write_cell(cell)
    entry = guidance.measure(cell, fallen=50.0, late_from=300.0, at=300.0)
    seed = entry["seeds"][1]
    assert seed["before_q_filter"] == {"generations": 4, "elite_fallen": 0.75,
                                       "beta_at_bound": 0.75, "guided": 0.5,
                                       "td3_fallen": 2 / 3, "td3_elite": 1 / 3}
    assert seed["after_q_filter"] == {"generations": 2, "elite_fallen": 0.0,
                                      "beta_at_bound": 0.5, "guided": 0.5,
                                      "td3_fallen": 0.0, "td3_elite": 0.0}
    assert seed["td3_late_median"] == 5.0            # of 7, 3 and 5
    # 250 and 350 lie as near 300: the earlier is reported
    assert seed["mu_near"] == {"env_steps": 250.0, "return": 20.0}
    assert seed["final_mu"] == 1234.0
    row = guidance.table({"c": entry}).splitlines()[-1]
    assert row == "| c | 1 | 4 / 2 | 75% | 75% / 50% | 50% / 50% | 67% | 33% | 5 | 20 | 1,234 |"


def test_until_counts_only_the_generations_up_to_it(tmp_path):
    cell = tmp_path / "figure4" / "walker2d" / "pgps"
    _write_cell(cell)
    seed = guidance.measure(cell, fallen=50.0, late_from=300.0, at=300.0, until=300)["seeds"][1]
    assert seed["before_q_filter"] == {"generations": 3, "elite_fallen": 2 / 3,
                                       "beta_at_bound": 2 / 3, "guided": 2 / 3,
                                       "td3_fallen": 0.5, "td3_elite": 0.5}
    assert seed["after_q_filter"]["generations"] == 0


def test_a_seed_without_late_evaluations_or_generations_of_a_phase_reports_none(tmp_path):
    cell = tmp_path / "figure4" / "walker2d" / "pgps"
    _write_cell(cell)
    entry = guidance.measure(cell, fallen=50.0, late_from=1e6, at=0.0)
    assert entry["seeds"][1]["td3_late_median"] is None
    only_before = guidance.phase_shares(GENERATIONS[:4], beta_max=8.0, fallen=50.0)
    assert only_before["after_q_filter"] == {"generations": 0, "elite_fallen": None,
                                             "beta_at_bound": None, "guided": None,
                                             "td3_fallen": None, "td3_elite": None}


def test_measure_refuses_a_missing_cell_another_algorithm_and_no_guidance(tmp_path):
    with pytest.raises(ValueError, match="no result.json"):
        guidance.measure(tmp_path / "nowhere", 50.0, 0.0, 0.0)
    cem = tmp_path / "figure4" / "walker2d" / "cem"
    _write_cell(cem, algo="cem")
    with pytest.raises(ValueError, match="a cell of cem"):
        guidance.measure(cem, 50.0, 0.0, 0.0)
    unguided = tmp_path / "figure5" / "swimmer" / "without_ea_guidance"
    _write_cell(unguided, ea_guides_pg=False)
    with pytest.raises(ValueError, match="ea_guides_pg"):
        guidance.measure(unguided, 50.0, 0.0, 0.0)

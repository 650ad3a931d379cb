"""The experiments' report: curves on a common grid, the interquartile mean and its stratified
bootstrap interval against their definitions, and the figures and table drawn from a results
folder beside the authors' curves."""

import json

import jax
import numpy as np
import pytest
from scipy import stats

from pgps_jax.cli import run_dir as rundir
from pgps_jax.experiments.paper import report


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8, 10, 11])
def test_iqm_is_the_quarter_trimmed_mean(n):
    scores = np.random.default_rng(n).normal(size=(3, n)) * 100
    np.testing.assert_allclose(report.iqm(scores), stats.trim_mean(scores, 0.25, axis=1),
                               rtol=1e-12)


def test_the_bootstrap_resamples_within_each_task():
    # Stratified: every resample holds four runs of each task, so the pooled IQM of four
    # zeros and four hundreds is always the mean of two of each (an unstratified bootstrap
    # would vary).
    tasks = [np.zeros(4), np.full(4, 100.0)]
    assert report.stratified_bootstrap_ci(tasks, jax.random.PRNGKey(3)) == (50.0, 50.0)


def test_the_bootstrap_interval_brackets_the_iqm_and_repeats_under_its_key():
    scores = [np.array([3000.0, 3500.0, 3600.0, 3700.0, 200.0])]
    low, high = report.stratified_bootstrap_ci(scores, jax.random.PRNGKey(0))
    assert low < report.iqm(scores[0]) < high
    assert 200.0 <= low and high <= 3700.0
    assert report.stratified_bootstrap_ci(scores, jax.random.PRNGKey(0)) == (low, high)


def test_curves_meet_on_the_grid_each_of_them_reached():
    a = (np.array([10_000.0, 30_000.0, 41_000.0]), np.array([0.0, 20.0, 31.0]))
    b = (np.array([5_000.0, 25_000.0]), np.array([1.0, 5.0]))
    curves = report.on_grid([a, b])
    np.testing.assert_array_equal(curves.steps, [10_000, 20_000, 30_000])  # b: to 25k + 10k
    np.testing.assert_allclose(curves.returns[0], [0.0, 10.0, 20.0])
    np.testing.assert_allclose(curves.returns[1], [2.0, 4.0, 5.0])


def _curve(path, steps, means):
    rundir.write_csv(path, rundir.eval_columns(1),
                     [[i, s, m, 0.0, m] for i, (s, m) in enumerate(zip(steps, means))])


def test_the_report_draws_each_run_beside_the_paper_and_tabulates_the_done_ones(tmp_path,
                                                                               monkeypatch):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes, subplots = [], plt.subplots

    def recording_subplots(**kwargs):
        fig, ax = subplots(**kwargs)
        axes.append(ax)
        return fig, ax

    monkeypatch.setattr(plt, "subplots", recording_subplots)
    out, reference = tmp_path / "results", tmp_path / "reference"
    steps = [10_000, 20_000, 30_000]
    done = out / "table1" / "ant" / "pgps"
    done.mkdir(parents=True)
    for seed, scale in zip((1, 2, 3), (1.0, 2.0, 4.0)):
        _curve(done / f"seed{seed}.csv", steps, [10 * scale, 20 * scale, 30 * scale])
    (done / "result.json").write_text(json.dumps(
        {"config": "pgps", "seeds": [1, 2, 3], "steps": 30_000,
         "env_steps": [30_000, 31_500, 30_200], "final": {"mu": [100.0, 250.0, 400.0]}}))
    running = out / "table1" / "ant" / "base"  # no result yet
    running.mkdir()
    _curve(running / "seed1.csv", steps[:2], [1.0, 2.0])
    (reference / "ant").mkdir(parents=True)
    for seed, last in ((1, 350.0), (2, 330.0)):
        _curve(reference / "ant" / f"{seed}.csv", steps, [0.0, 100.0, last])

    written = report.write_report("table1", out, reference)

    figure, table = out / "table1" / "ant.png", out / "table1" / report.REPORT
    assert written == [figure, out / "table1" / "table1.md", table]
    assert len((out / "table1" / "table1.md").read_text().splitlines()) == 2  # no base done
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [t.get_text() for t in axes[0].get_legend().get_texts()] == [
        "ours: base (1 seed)", "ours: pgps (3 seeds)", "paper: PGPS (2 seeds)"]
    rows = [line.split(" | ") for line in table.read_text().splitlines()[2:]]
    ours = np.array([100.0, 250.0, 400.0])
    low, high = report.stratified_bootstrap_ci([ours], jax.random.PRNGKey(report.BOOTSTRAP_SEED))
    assert rows[0] == ["| ant", "ours: pgps", "30,000–31,500", "100 250 400",
                       f"250 ± {ours.std(ddof=1):.0f}",
                       f"250 [{low:,.0f}, {high:,.0f}] |"]
    assert rows[1][:5] == ["| ant", "paper: PGPS", "30,000", "350 330", "340 ± 14"]
    assert len(rows) == 2  # the running cell is drawn, not tabulated
    curves, finals, _ = report._ours(running)
    assert finals is None and curves.returns.tolist() == [[1.0, 2.0]]


def test_figure5_reports_the_td3_actor_without_the_paper_s_mu(tmp_path):
    out, reference = tmp_path / "results", tmp_path / "reference"
    cell = out / "figure5" / "swimmer" / "without_ea_guidance"
    cell.mkdir(parents=True)
    _curve(cell / "seed1.csv", [10_000, 20_000], [5.0, 6.0])
    _curve(cell / "seed1_td3.csv", [10_000, 20_000], [50.0, 60.0])
    (cell / "result.json").write_text(json.dumps(
        {"config": "without_ea_guidance", "seeds": [1], "steps": 20_000, "env_steps": [20_000],
         "final": {"mu": [6.0], "td3": [61.0], "elite": [7.0]}}))
    (reference / "swimmer").mkdir(parents=True)
    _curve(reference / "swimmer" / "1.csv", [10_000, 20_000], [0.0, 300.0])

    report.write_report("figure5", out, reference)

    rows = (out / "figure5" / report.REPORT).read_text().splitlines()[2:]
    assert rows == ["| swimmer | ours: without_ea_guidance | 20,000 | 61 | 61 ± 0 | 61 [61, 61] |"]
    curves, _, _ = report._ours(cell, "td3")
    assert curves.returns.tolist() == [[50.0, 60.0]]


def test_figure6_compares_the_q_filtered_actors_with_the_sampled_ones(tmp_path):
    cell = tmp_path / "results" / "figure6" / "halfcheetah" / "pgps"
    cell.mkdir(parents=True)
    header = ["generation", "env_steps", "q_filter_active", "td3_in_population",
              "return_0", "return_1", "return_2", "return_3"]
    rundir.write_csv(cell / "seed1_generations.csv", header, [
        [1, 5_000, 0, 1, 9.0, 9.0, 9.0, 9.0],      # before Q-filtering: left out
        [2, 12_000, 1, 1, 100.0, 10.0, 30.0, 70.0],  # slot 3 is the TD3 actor's
        [3, 15_000, 1, 0, 100.0, 20.0, 40.0, 60.0]])
    steps, filtered, sampled = report.filtered_and_sampled(cell / "seed1_generations.csv")
    np.testing.assert_array_equal(steps, [12_000, 15_000])
    np.testing.assert_array_equal(filtered, [30.0, 50.0])
    np.testing.assert_array_equal(sampled, [10.0, 20.0])
    _curve(cell / "seed1.csv", [10_000, 20_000], [1.0, 2.0])

    written = report.write_report("figure6", tmp_path / "results", tmp_path / "none")

    figure = tmp_path / "results" / "figure6" / "halfcheetah_pgps_q_filter.png"
    assert figure in written and figure.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("steps, marker", [([5_000, 12_000], "o"),
                                           ([5_000, 15_000, 25_000], "None")])
def test_figure6_marks_a_curve_of_one_point_which_a_line_alone_would_not_show(tmp_path, steps,
                                                                              marker):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    header = ["generation", "env_steps", "q_filter_active", "td3_in_population",
              "return_0", "return_1", "return_2", "return_3"]
    rundir.write_csv(tmp_path / "seed1_generations.csv", header, [
        [g + 1, s, 1, 0, 10.0, 20.0, 30.0, 40.0] for g, s in enumerate(steps)])
    axes = []

    class Recording:  # pyplot, keeping the figure's axes
        def subplots(self, **kwargs):
            fig, ax = plt.subplots(**kwargs)
            axes.append(ax)
            return fig, ax

        close = staticmethod(plt.close)

    report._draw_q_filter(tmp_path, tmp_path / "figure.png", "halfcheetah", Recording())
    lines = axes[0].get_lines()
    assert len(lines) == 2 and {len(line.get_xdata()) for line in lines} == {len(steps) - 1}
    assert [line.get_marker() for line in lines] == [marker, marker]


def test_binned_means_average_each_finished_span_then_the_seeds():
    a = (np.array([5_000.0, 10_000.0, 15_000.0, 21_000.0, 30_000.0]),
         np.array([1.0, 2.0, 4.0, 8.0, 100.0]))
    b = (np.array([12_000.0, 25_000.0]), np.array([10.0, np.nan]))
    ends, means = report.binned_means([a, b])
    # spans [0, 10k) and [10k, 20k) are finished by both (b's last point lies in [20k, 30k));
    # b has no value in the first; a's [10k, 20k) mean is 3
    np.testing.assert_array_equal(ends, [10_000, 20_000])
    np.testing.assert_allclose(means, [1.0, (3.0 + 10.0) / 2])


def test_no_results_is_a_usage_error(tmp_path):
    with pytest.raises(report.UsageError, match="no results of figure4 under"):
        report.write_report("figure4", tmp_path, tmp_path)


def test_the_summary_of_cells_under_way_draws_them_without_a_table_of_final_returns(tmp_path):
    from pgps_jax.experiments.paper import command
    running = tmp_path / "figure4" / "hopper" / "pgps"  # curves so far, no result yet
    running.mkdir(parents=True)
    _curve(running / "seed1.csv", [10_000, 20_000], [1.0, 2.0])
    written = command.write_summary("figure4", tmp_path, tmp_path / "reference")
    assert written == [tmp_path / "figure4" / "hopper.png", tmp_path / "figure4" / report.REPORT]
    assert not (tmp_path / "figure4" / command.FINAL_RETURNS).exists()


def test_a_run_is_labelled_with_what_it_changed_from_its_cell_s_configuration():
    import dataclasses
    from pgps_jax.agent.config import for_task
    from pgps_jax.experiments.paper.grid import Cell
    cell = Cell("swimmer", "without_ea_guidance", {"ea_guides_pg": False})
    as_run = json.loads(json.dumps(dataclasses.asdict(for_task("swimmer", ea_guides_pg=False))))

    def result(config, env, task="swimmer"):  # run on today's physics, with `env`'s changes
        from pgps_jax.envs import make_env
        return {"settings": {"config": config, "env": env,
                             "physics": make_env(task, **env).settings()}}
    assert report.run_label(cell.config, result(as_run, {}), cell) == "ours: without_ea_guidance"
    changed = {**as_run, "resample_before_q_filter": True, "actor_hidden": [16]}
    assert report.run_label(cell.config, result(changed, {"iterations": 4}), cell) == (
        "ours: without_ea_guidance (actor_hidden=[16], resample_before_q_filter=true, "
        "iterations=4)")
    assert report.run_label("brax_sac", {"final": {}}, None) == "ours: brax_sac"
    # without Q-filtering the population is sampled every generation whatever the switch says
    td3 = Cell("hopper", "td3", {}, "td3")
    inert = json.loads(json.dumps(dataclasses.asdict(
        for_task("hopper", "td3", resample_before_q_filter=True))))
    assert report.run_label(td3.config, result(inert, {}, "hopper"), td3) == "ours: td3"
    # a cell saved before the switch existed was resampled
    older = {k: v for k, v in as_run.items() if k != "resample_before_q_filter"}
    assert report.run_label(cell.config, result(older, {}), cell) == (
        "ours: without_ea_guidance (resample_before_q_filter=true)")


def test_a_run_on_an_earlier_physics_of_its_task_is_labelled_with_it():
    """halfcheetah's cells from before the physics was recorded ran with one Newton
    iteration, at JAX's default precision; a cell that records today's physics shows none."""
    import dataclasses
    from pgps_jax.agent.config import for_task
    from pgps_jax.envs import make_env
    from pgps_jax.experiments.paper.grid import Cell
    cell = Cell("halfcheetah", "pgps", {})
    config = json.loads(json.dumps(dataclasses.asdict(for_task("halfcheetah"))))
    before = {"settings": {"config": config, "env": {}}}
    assert report.run_label("pgps", before, cell) == (
        "ours: pgps (iterations=1, matmul_precision=default)")
    today = {"settings": {"config": config, "env": {},
                          "physics": make_env("halfcheetah").settings()}}
    assert report.run_label("pgps", today, cell) == "ours: pgps"


def test_table1_normalises_each_task_by_the_base_model_s_better_actor():
    def result(mu, td3, wall):
        return {"final": {"mu": mu, "td3": td3}, "wall_s": wall,
                "seeds": list(range(1, len(mu) + 1))}
    done = {("walker2d", "base"): result([100.0, 200.0], [150.0, 100.0], 100.0),
            ("walker2d", "pgps"): result([350.0, 350.0], [0.0, 0.0], 110.0),
            ("ant", "base"): result([10.0, 10.0], [20.0, 0.0], 50.0),
            ("ant", "pgps"): result([30.0, 30.0], [0.0, 0.0], 65.0),
            ("halfcheetah", "q_filter"): result([1.0], [1.0], 1.0)}  # no base there: left out
    # base per run: the better of μ and TD3 -> walker2d 175, ant 15; pgps 350 and 30 -> 2 both
    assert report.table1_rows(done) == [["base", "1.00", "1.000", "walker2d ant"],
                                        ["pgps", "2.00", "1.200", "walker2d ant"]]


def test_table1_scores_a_model_on_the_seeds_it_shares_with_the_base_model():
    """Figure 4's 10-seed PGPS cell reused in a 5-seed Table 1: its seeds 6-10 left out."""
    done = {("ant", "base"): {"final": {"mu": [10.0, 20.0], "td3": [0.0, 0.0]},
                              "wall_s": 1.0, "seeds": [1, 2]},
            ("ant", "pgps"): {"final": {"mu": [60.0, 30.0, 1e6], "td3": [0.0] * 3},
                              "wall_s": 1.0, "seeds": [2, 1, 3]}}
    # base 15; pgps on seeds 1 and 2: (30 + 60) / 2 = 45 -> 3
    assert report.table1_rows(done)[1] == ["pgps", "3.00", "–", "ant"]


def test_table1_compares_wall_clocks_only_of_cells_that_ran_alike():
    """A cell of other seeds, or run in parts (its wall-clock the sum of its programs'), is
    scored but not timed against the Base model's."""
    def result(seeds, wall, parts=()):
        r = {"final": {"mu": [2.0] * len(seeds), "td3": [0.0] * len(seeds)}, "wall_s": wall,
             "seeds": seeds}
        return {**r, "parts": [{"seeds": p} for p in parts]} if parts else r
    done = {("walker2d", "base"): result([1, 2], 100.0),
            ("ant", "base"): result([1, 2], 50.0),
            ("walker2d", "pgps"): result([1, 2, 3], 150.0),  # a third seed
            ("ant", "pgps"): result([1, 2], 60.0),
            ("walker2d", "q_filter"): result([1, 2], 300.0, parts=([1], [2])),
            ("ant", "q_filter"): result([1, 2], 55.0, parts=([1], [2]))}
    assert report.table1_rows(done) == [["base", "1.00", "1.000", "walker2d ant"],
                                        ["pgps", "1.00", "1.200 (ant)", "walker2d ant"],
                                        ["q_filter", "1.00", "–", "walker2d ant"]]
    done[("ant", "base")] = result([1, 2], 50.0, parts=([1], [2]))  # now run as q_filter ran
    assert report.table1_rows(done)[2] == ["q_filter", "1.00", "1.100 (ant)", "walker2d ant"]
    done[("walker2d", "base")] = result([1, 2, 3], 100.0, parts=([1, 2], [3]))
    done[("walker2d", "q_filter")] = result([1, 2, 3], 300.0, parts=([1], [2, 3]))
    assert report.table1_rows(done)[2] == ["q_filter", "1.00", "1.100 (ant)", "walker2d ant"]
    done[("walker2d", "q_filter")] = result([1, 2, 3], 300.0, parts=([1, 2], [3]))
    assert report.table1_rows(done)[2] == ["q_filter", "1.00", "2.050", "walker2d ant"]


def test_figure4_reports_each_algorithms_actor_and_the_peers_found_beside_them(tmp_path):
    """TD3 alone reports its actor (`seed<k>.csv`, the first of its final returns), a peer's
    folder with a result.json (benchmarks.peers) joins the figure and the table."""
    out, reference = tmp_path / "results", tmp_path / "reference"
    (reference / "hopper").mkdir(parents=True)
    _curve(reference / "hopper" / "1.csv", [10_000, 20_000], [0.0, 100.0])
    for config, final in (("td3", {"td3": [123.0, 125.0]}),
                          ("brax_sac", {"policy": [321.0, 323.0]})):
        cell = out / "figure4" / "hopper" / config
        cell.mkdir(parents=True)
        for seed in (1, 2):
            _curve(cell / f"seed{seed}.csv", [10_000, 20_000], [1.0, final[next(iter(final))][0]])
        (cell / "result.json").write_text(json.dumps(
            {"config": config, "seeds": [1, 2], "steps": 20_000, "env_steps": [20_000] * 2,
             "final": final}))
    report.write_report("figure4", out, reference)
    table = (out / "figure4" / report.REPORT).read_text()
    assert "| hopper | ours: td3 | 20,000 | 123 125 |" in table
    assert "| hopper | ours: brax_sac | 20,000 | 321 323 |" in table
    assert (out / "figure4" / "hopper.png").exists()

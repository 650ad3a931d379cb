"""The paper's experiment runner on tiny cells of hopper (real MJX physics): its outputs in the
authors' format, a cut-off cell that continues exactly, seeds split over two devices, and its
command line's errors."""

import dataclasses
import fcntl
import json
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys

import jax
import numpy as np
import pytest

from benchmarks import lockstep
from pgps_jax.agent.config import PGPSConfig, for_task
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.assignments import assignments, env_assignments, field_types
from pgps_jax.cli.checkpoint import Checkpoints
from pgps_jax.cli.errors import RunFailed, UsageError
from pgps_jax.envs import make_env
from pgps_jax.experiments.paper import command, grid, report, runner, side_by_side

from conftest import REDUCED_CELL, REDUCED_PGPS
from train_cli import REPO, cli_env, read_csv, run_here, wait_until

TINY, BUDGET = REDUCED_PGPS, REDUCED_CELL
HOPPER = grid.Cell("hopper", "pgps", {})

pytestmark = pytest.mark.xdist_group("paper")  # one worker runs the uninterrupted cell once


class Stop(Exception):
    pass


def _timeless(result: dict) -> dict:
    """`result` without its wall-clock seconds (those of its parts included)."""
    clock = {"wall_s": 0, "wall_split_s": {}}
    return {**result, **clock, "parts": [{**p, **clock} for p in result.get("parts", [])]}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    results = command.run("figure4", out, BUDGET, tasks=["hopper"], configs=["pgps"],
                          progress=False)
    return out, results


def test_a_cell_writes_the_authors_csv_per_seed_and_the_final_returns(uninterrupted):
    out, (result,) = uninterrupted
    cell = out / "figure4" / "hopper" / "pgps"
    assert result["seeds"] == [1, 2] and min(result["env_steps"]) >= BUDGET.steps
    split = result["wall_split_s"]
    assert list(split) == list(runner.WALL_SPLIT) and min(split.values()) > 0
    assert sum(split.values()) < result["wall_s"]
    for seed in (1, 2):
        curves = {actor: read_csv(cell / runner.seed_file(seed, actor))
                  for actor in ("", "td3", "elite")}
        assert runner.seed_file(seed) == f"seed{seed}.csv"
        for header, rows in curves.values():
            assert header == ["", "Step", "Mean", "Std", "Reward1", "Reward2"]
            steps = [int(r["Step"]) for r in rows]
            assert steps[0] == 200 and steps == sorted(steps) and steps[-1] <= BUDGET.steps
            for r in rows:
                rewards = [float(r["Reward1"]), float(r["Reward2"])]
                assert float(r["Mean"]) == pytest.approx(np.mean(rewards), rel=1e-6)
                assert float(r["Std"]) == pytest.approx(np.std(rewards), rel=1e-5, abs=1e-6)
        assert [r["Step"] for r in curves["td3"][1]] == [r["Step"] for r in curves[""][1]]
        assert [r["Mean"] for r in curves["td3"][1]] != [r["Mean"] for r in curves[""][1]]
        header, rows = read_csv(cell / f"seed{seed}_generations.csv")
        assert header == ["generation", "env_steps", "T", "rollout_steps", "q_filter_active",
                          "td3_in_population", "return_0", "return_1", "elite_return",
                          "td3_return", "guided_loss", "beta", "cem_var_mean", "cem_damping"]
        for r in rows:  # the generation's elite is its best return
            assert float(r["elite_return"]) == pytest.approx(
                max(float(r["return_0"]), float(r["return_1"])), rel=1e-6)
            # an episode, or test episodes that had to end (their limit the evaluation's)
            assert 1 <= int(r["rollout_steps"]) <= max(int(r["T"]), BUDGET.evaluation.steps)
        assert [int(r["generation"]) for r in rows] == list(range(1, len(rows) + 1))
        assert len(rows) <= result["generations"]
        began = [TINY["warmup_steps"]] + [int(r["env_steps"]) for r in rows[:-1]]
        assert [int(r["q_filter_active"]) for r in rows] == [
            int(step >= TINY["q_filter_start"]) for step in began]
    header, rows = read_csv(out / "figure4" / command.FINAL_RETURNS)
    assert header == ["task", "config", "seed", "env_steps", "elite_final", "mu_final",
                      "td3_final"]
    assert [(r["task"], r["seed"]) for r in rows] == [("hopper", "1"), ("hopper", "2")]
    assert [float(r["mu_final"]) for r in rows] == pytest.approx(result["final"]["mu"])
    assert json.loads((cell / runner.RESULT).read_text()) == result
    assert not (cell / "checkpoints").exists()  # a done cell keeps its results only
    header, rows = read_csv(cell / runner.GENERATION_TIMES)
    assert header == ["generation", "play_s", "learn_s", "rollout_steps"]
    assert [int(r["generation"]) for r in rows] == list(range(1, result["generations"] + 1))
    assert all(float(r["play_s"]) > 0 and float(r["learn_s"]) > 0 for r in rows)
    # the program's rollout is as long as its seeds' longest: in all, at least each seed's
    # own steps and at most their sum
    program = [int(r["rollout_steps"]) for r in rows]
    own = [sum(int(r["rollout_steps"]) for r in read_csv(cell / f"seed{seed}_generations.csv")[1])
           for seed in (1, 2)]
    assert min(program) >= 1 and max(own) <= sum(program) <= sum(own)


def test_each_seed_stops_at_its_own_budget(uninterrupted):
    """A seed that reaches the budget waits for the others: its last generation is the one
    that took it there, and its result is of that state."""
    out, (result,) = uninterrupted
    cell = out / "figure4" / "hopper" / "pgps"
    generations = []
    for seed in (1, 2):
        _, rows = read_csv(cell / f"seed{seed}_generations.csv")
        steps = [int(r["env_steps"]) for r in rows]
        assert steps[-2] < BUDGET.steps <= steps[-1] == result["env_steps"][seed - 1]
        generations.append(len(rows))
    if jax.default_backend() == "cpu":  # these seeds' CPU trajectories reach it apart
        assert generations[0] != generations[1]
    assert result["generations"] >= max(generations)
    assert not (cell / runner.AT_BUDGET).exists()


def test_at_budget_keeps_the_records_up_to_the_generation_a_cell_continues_from(tmp_path):
    class Agent:
        def evaluated_actors(self, state):
            return state

    budget = runner.Budget(steps=500, seeds=2)
    path = tmp_path / runner.AT_BUDGET
    first = runner.AtBudget.read(path, budget.seeds, 0)
    first.record(1, np.array([400, 300]), np.zeros((2, 3, 4)), Agent(), budget, path)
    assert not path.exists()
    first.record(2, np.array([520, 450]), np.ones((2, 3, 4)), Agent(), budget, path)
    continued = runner.AtBudget.read(path, budget.seeds, 2)
    continued.record(3, np.array([560, 510]), np.full((2, 3, 4), 2.0), Agent(), budget, path)
    assert continued.steps.tolist() == [520, 510]
    sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    actors = np.asarray(continued.actors_of(np.full((2, 3, 4), 3.0), Agent(), sharding))
    np.testing.assert_array_equal(actors, np.stack([np.ones((3, 4)), np.full((3, 4), 2.0)]))
    # from the checkpoint of generation 2 again: seed 2's record (generation 3) is made anew
    again = runner.AtBudget.read(path, budget.seeds, 2)
    assert again.steps.tolist() == [520, 0] and again.actors[1] is None
    assert runner.AtBudget.read(path, budget.seeds, 0).actors == [None, None]


def test_a_done_cell_is_not_run_again(uninterrupted):
    out, (result,) = uninterrupted
    before = (out / "figure4" / "hopper" / "pgps" / runner.RESULT).stat().st_mtime_ns

    def never(generation, steps):
        raise AssertionError("a done cell trained")
    again = runner.run_cell(HOPPER, out / "figure4" / "hopper" / "pgps", BUDGET, never)
    assert again == result
    assert (out / "figure4" / "hopper" / "pgps" / runner.RESULT).stat().st_mtime_ns == before


def test_the_lockstep_benchmark_sums_the_program_s_and_each_seed_s_rollout_steps(
        uninterrupted, in_parts, tmp_path):
    out, (result,) = uninterrupted
    cell = out / "figure4" / "hopper" / "pgps"
    (measured,) = lockstep.lockstep(cell)
    times = np.loadtxt(cell / runner.GENERATION_TIMES, delimiter=",", skiprows=1, ndmin=2)
    own = [np.loadtxt(cell / f"seed{seed}_generations.csv", delimiter=",", skiprows=1,
                      usecols=(1, 3), ndmin=2) for seed in (1, 2)]
    assert measured["program"] == runner.GENERATION_TIMES
    assert measured["generations"] == result["generations"] == len(times)
    assert measured["program_rollout_steps"] == times[:, 3].sum()
    assert [s["rollout_steps"] for s in measured["seeds"]] == [o[:, 1].sum() for o in own]
    assert [s["env_steps"] for s in measured["seeds"]] == [o[-1, 0] for o in own]
    assert measured["program_over_longest_seed"] == pytest.approx(
        times[:, 3].sum() / max(o[:, 1].sum() for o in own), abs=1e-3)
    assert measured["play_s"] == pytest.approx(times[:, 1].sum(), abs=0.05)
    # a program of one seed waits on no other: it plays its seed's own steps
    parts = lockstep.lockstep(in_parts[0] / "figure4" / "hopper" / "pgps")
    assert [(p["program"], [s["seed"] for s in p["seeds"]]) for p in parts] == [
        ("generation_times_seeds1-1.csv", [1]), ("generation_times_seeds2-2.csv", [2])]
    assert all(p["program_over_longest_seed"] == 1 for p in parts)
    # a cell given more seeds: the whole cell's program holds the seeds no part holds
    given = tmp_path / "given"
    given.mkdir()
    for name in [f"seed{k}_generations.csv" for k in range(1, 11)] + [
            runner.GENERATION_TIMES, "generation_times_seeds6-10.csv"]:
        (given / name).touch()
    assert [(path.name, seeds) for path, seeds in lockstep.programs(given)] == [
        (runner.GENERATION_TIMES, [1, 2, 3, 4, 5]),
        ("generation_times_seeds6-10.csv", [6, 7, 8, 9, 10])]
    # a cell whose files do not record it is refused, naming why
    lost = shutil.copytree(in_parts[0] / "figure4" / "hopper" / "pgps", tmp_path / "lost")
    (lost / "seed2_generations.csv").unlink()  # a part's seeds are in its times file's name
    with pytest.raises(ValueError, match="missing .seed2_generations.csv"):
        lockstep.lockstep(lost)
    older = shutil.copytree(cell, tmp_path / "older")
    rows = (older / runner.GENERATION_TIMES).read_text().splitlines()
    (older / runner.GENERATION_TIMES).write_text(
        "\n".join(",".join(row.split(",")[:3]) for row in rows) + "\n")
    with pytest.raises(ValueError, match="no rollout_steps column"):
        lockstep.lockstep(older)
    (older / runner.GENERATION_TIMES).unlink()
    with pytest.raises(ValueError, match="has no generation_times.csv"):
        lockstep.lockstep(older)
    with pytest.raises(ValueError, match="not a directory"):
        lockstep.lockstep(tmp_path / "absent")


def test_the_report_alone_writes_the_table_of_final_returns_again(uninterrupted):
    out, _ = uninterrupted
    table = out / "figure4" / command.FINAL_RETURNS
    before = table.read_text()
    table.unlink()
    assert command.main(["figure4", "--report", "--out", str(out),
                         "--reference", str(REPO / command.REFERENCE)]) == 0
    assert table.read_text() == before


def test_the_table_of_final_returns_keeps_its_columns_whichever_cell_comes_first(tmp_path):
    pgps = {"task": "ant", "config": "pgps", "seeds": [1], "env_steps": [1000],
            "final": {"mu": [5.0], "td3": [4.0], "elite": [3.0]}}
    sac = {"task": "hopper", "config": "brax_sac", "seeds": [1], "env_steps": [999],
           "final": {"policy": [2.0]}}
    tables = []
    for name, results in (("a.csv", [pgps, sac]), ("b.csv", [sac, pgps])):
        command.write_final_returns(tmp_path / name, results)
        header, rows = read_csv(tmp_path / name)
        tables.append((header, sorted(map(tuple, (r.values() for r in rows)))))
    assert tables[0] == tables[1]
    assert tables[0][0][4:] == ["elite_final", "mu_final", "policy_final", "td3_final"]


def test_a_cell_run_with_other_settings_is_refused(uninterrupted):
    out, _ = uninterrupted
    longer = dataclasses.replace(BUDGET, steps=800)
    with pytest.raises(UsageError, match="steps: 600 there, 800 now"):
        command.run("figure4", out, longer, tasks=["hopper"], configs=["pgps"],
                    progress=False)
    other = dataclasses.replace(BUDGET, overrides=BUDGET.overrides + (("ss1_size", 4),))
    with pytest.raises(UsageError, match="config.ss1_size: 8 there, 4 now"):
        command.run("figure4", out, other, tasks=["hopper"], configs=["pgps"],
                    progress=False)
    contacts = dataclasses.replace(BUDGET, env=(("iterations", 2),))
    with pytest.raises(UsageError, match="physics: {.*'iterations': 1.*} there, {.*"
                                         "'iterations': 2.*} now"):
        command.run("figure4", out, contacts, tasks=["hopper"], configs=["pgps"],
                    progress=False)
    result = json.loads((out / "figure4" / "hopper" / "pgps" / runner.RESULT).read_text())
    assert result["settings"]["physics"] == {
        "start_pose": "qpos0", "integrator": "euler", "solver": "newton", "iterations": 1,
        "ls_iterations": 4, "euler_damping": False, "floor_contacts": "model",
        "matmul_precision": "highest", "impl": "jax"}
    # `--env` arguments that change only how the physics is computed are the same cell
    speed_only = {**result["settings"], "env": {"unroll_solver": False},
                  "physics": make_env("hopper", unroll_solver=False).settings()}
    runner._require_same(out, result["settings"], speed_only, "hopper", done=True)
    before_env = {k: v for k, v in result["settings"].items() if k != "env"}
    runner._require_same(out, before_env, result["settings"], "hopper")  # from before --env


def test_settings_differing_counts_the_env_arguments_through_their_physics():
    """The `--env` arguments of a task with MJX physics count only through the physics they
    give; those of an env without it count as themselves; `ignored` settings do not count."""
    mjx = {"physics": {"iterations": 3}, "env": {"fused_solve": False}, "steps": 10}
    assert runner.settings_differing({**mjx, "env": {}}, mjx, "env") == []
    assert runner.settings_differing({**mjx, "steps": 20}, mjx, "env") == ["steps"]
    assert runner.settings_differing({**mjx, "physics": {"iterations": 1}}, mjx,
                                     "env") == ["physics"]
    assert runner.settings_differing({**mjx, "steps": 20}, mjx, "env", {"steps"}) == []
    assert runner.settings_differing({"env": {}}, mjx, "env") == ["physics", "steps"]  # in order
    point_mass = {"physics": None, "--env": {"goal": 1.0}}
    assert runner.settings_differing({**point_mass, "--env": {}}, point_mass,
                                     "--env") == ["--env"]


def test_a_cell_from_before_the_physics_was_recorded_ran_on_the_physics_of_then():
    """A result without `physics` counts as run on the task's physics of that time, with its
    `--env` arguments: JAX's default matrix products (`matmul_precision=default`) and
    otherwise hopper's of today, walker2d's and halfcheetah's solved with one Newton
    iteration and the ant's with two (not three)."""
    then_products = (("matmul_precision", "default"),)

    def settings(task, env=()):
        return runner._settings("pgps", for_task(task), dataclasses.replace(
            BUDGET, env=then_products + env), 1, make_env(task, **dict(then_products + env)))
    for task in ("hopper", "walker2d", "halfcheetah", "ant"):
        now = settings(task)
        before = {**now, "env": {}}
        before.pop("physics")
        if task == "hopper":
            runner._require_same(pathlib.Path("cell"), before, now, task)
        else:
            then = 2 if task == "ant" else 1
            with pytest.raises(UsageError, match=f"'iterations': {then}.*'iterations': 3"):
                runner._require_same(pathlib.Path("cell"), before, now, task)
    with pytest.raises(UsageError, match="'matmul_precision': 'default'.*'matmul_precision': "
                                         "'highest'"):
        runner._require_same(pathlib.Path("cell"), before, runner._settings(
            "pgps", for_task("ant"), BUDGET, 1, make_env("ant")), "ant")
    # one run then with `--env iterations=3` ran on today's iterations
    now = settings("walker2d", (("iterations", 3),))
    runner._require_same(pathlib.Path("cell"), {**{k: v for k, v in now.items()
                                                   if k != "physics"},
                                                "env": {"iterations": 3}}, now, "walker2d")


def test_a_recorded_physics_from_before_matmul_precision_had_the_platform_s_products():
    """Physics recorded before `matmul_precision` existed ran with JAX's default products:
    not today's float32 ones, the same as a run today with matmul_precision=default."""
    now = runner._settings("pgps", for_task("hopper"), BUDGET, 1, make_env("hopper"))
    before = {**now, "physics": {k: v for k, v in now["physics"].items()
                                 if k != "matmul_precision"}}
    with pytest.raises(UsageError, match="'matmul_precision': 'default'.*'matmul_precision': "
                                         "'highest'"):
        runner._require_same(pathlib.Path("cell"), before, now, "hopper")
    as_then = runner._settings("pgps", for_task("hopper"), dataclasses.replace(
        BUDGET, env=(("matmul_precision", "default"),)), 1,
        make_env("hopper", matmul_precision="default"))
    runner._require_same(pathlib.Path("cell"), before, as_then, "hopper")


def test_a_cell_from_before_beta_adapted_existed_adapted_beta_before_each_block():
    """A cell saved before `beta_adapted` existed adapted β before each block (Algorithm 1),
    today's default: it continues under it, not under the authors' order."""
    now = runner._settings("pgps", for_task("hopper"), BUDGET, 1, make_env("hopper"))
    before = {**now, "config": {k: v for k, v in now["config"].items() if k != "beta_adapted"}}
    runner._require_same(pathlib.Path("cell"), before, now, "hopper")
    after = runner._settings("pgps", for_task("hopper", beta_adapted="after_block"), BUDGET, 1,
                             make_env("hopper"))
    with pytest.raises(UsageError, match="config.beta_adapted: 'before_block' there, "
                                         "'after_block' now"):
        runner._require_same(pathlib.Path("cell"), before, after, "hopper")


def test_a_cell_from_before_any_later_field_ran_it_as_it_was_then():
    """A cell saved before later PGPSConfig fields existed ran them at their defaults, or at
    their values then (`VALUES_BEFORE_ADDED`, e.g. the guiding rule mean − std): it continues
    where today's configuration has those values, and is refused where it does not."""
    from pgps_jax.agent.config import VALUES_BEFORE_ADDED
    later = ("elitism", "policy_delay", "exploration_noise", "exploring_episodes",
             "beta_adapted", "target_actor_from_elite")
    now = runner._settings("pgps", for_task("hopper"), BUDGET, 1, make_env("hopper"))
    before = {**now, "config": {k: v for k, v in now["config"].items()
                                if k not in later and k not in VALUES_BEFORE_ADDED}}
    as_then = runner._settings("pgps", for_task("hopper", **VALUES_BEFORE_ADDED), BUDGET, 1,
                               make_env("hopper"))
    runner._require_same(pathlib.Path("cell"), before, as_then, "hopper")
    with pytest.raises(UsageError, match="config.fell_behind_rule: 'mean_minus_std' there, "
                                         "'mean' now"):
        runner._require_same(pathlib.Path("cell"), before, now, "hopper")
    from_elite = runner._settings("pgps", for_task("hopper", **VALUES_BEFORE_ADDED,
                                                   target_actor_from_elite=True), BUDGET, 1,
                                  make_env("hopper"))
    with pytest.raises(UsageError, match="config.target_actor_from_elite: False there, "
                                         "True now"):
        runner._require_same(pathlib.Path("cell"), before, from_elite, "hopper")


def test_a_recorded_physics_from_before_impl_ran_on_jax():
    """Physics recorded before `impl` existed ran on MJX's JAX implementation: the same as a
    cell run today on it, not as one on Warp."""
    now = runner._settings("pgps", for_task("hopper"), BUDGET, 1, make_env("hopper"))
    before = {**now, "physics": {k: v for k, v in now["physics"].items() if k != "impl"}}
    runner._require_same(pathlib.Path("cell"), before, now, "hopper")
    on_warp = {**now, "physics": {**now["physics"], "impl": "warp"}}
    with pytest.raises(UsageError, match="'impl': 'jax'.*'impl': 'warp'"):
        runner._require_same(pathlib.Path("cell"), before, on_warp, "hopper")


def test_set_reads_values_as_the_training_command_line_does():
    parsed = assignments(["resample_before_q_filter=false", "actor_hidden=[16,16]",
                          "pop_size=4", "sigma_init=1e-3"], "--set", field_types(PGPSConfig))
    assert parsed == {"resample_before_q_filter": False, "actor_hidden": (16, 16),
                      "pop_size": 4, "sigma_init": 1e-3}
    env = env_assignments(["floor_contacts=gym", "iterations=2", "euler_damping=true",
                           "unroll_line_search=false", "write_out_linalg=null"])
    assert env == {"floor_contacts": "gym", "iterations": 2, "euler_damping": True,
                   "unroll_line_search": False, "write_out_linalg": None}


def test_an_unknown_name_or_a_bad_value_is_refused_with_the_choices():
    with pytest.raises(UsageError, match="'iteration=2'.*NAME one of start_pose, integrator"):
        env_assignments(["iteration=2"])
    with pytest.raises(UsageError,
                       match=r"--env: integrator must be one of "
                             r"\['euler', 'implicitfast', 'rk4'\]"):
        env_assignments(["integrator=rk5"])
    with pytest.raises(UsageError,
                       match="--env: unknown start_pose 'standing'; valid: qpos0, init_qpos"):
        env_assignments(["start_pose=standing"])
    with pytest.raises(UsageError, match="unroll_line_search must be true or false"):
        env_assignments(["unroll_line_search=maybe"])
    with pytest.raises(UsageError, match="'pop_size'.*NAME one of pop_size, top_k"):
        assignments(["pop_size"], "--set", field_types(PGPSConfig))
    with pytest.raises(UsageError, match="--set pop_size"):
        assignments(["pop_size=many"], "--set", field_types(PGPSConfig))


def test_a_cut_off_cell_continues_from_its_checkpoint_to_the_same_result(uninterrupted,
                                                                         tmp_path, monkeypatch):
    out, (result,) = uninterrupted
    directory = tmp_path / "cell"

    def cut_off(generation, steps):
        if generation == 3:
            raise Stop
    with pytest.raises(Stop):
        runner.run_cell(HOPPER, directory, BUDGET, cut_off)
    assert not (directory / runner.RESULT).exists()
    with monkeypatch.context() as patch:  # a runner whose generations have one more column
        columns = runner._population_metrics
        patch.setattr(runner, "_population_metrics", lambda agent: columns(agent)[:1] * 2
                      + columns(agent)[1:])
        with pytest.raises(UsageError, match="older runner .*per-generation columns"):
            runner.run_cell(HOPPER, directory, BUDGET)
    checkpoints = Checkpoints(directory / runner.CHECKPOINTS)
    before = checkpoints.latest_meta()[1]["wall_split_s"]
    checkpoints.close()
    generations = []
    resumed = runner.run_cell(HOPPER, directory, BUDGET,
                              lambda generation, steps: generations.append(generation))
    assert generations[0] == 3  # from the checkpoint of generation 2
    assert _timeless(resumed) == _timeless(result)
    split = resumed["wall_split_s"]  # the cut-off run's seconds carried on
    assert all(split[key] >= before[key] for key in runner.WALL_SPLIT)
    assert split["compile"] > before["compile"] > 0
    for seed in (1, 2):
        for name in (runner.seed_file(seed), runner.seed_file(seed, "td3"),
                     runner.seed_file(seed, "elite"), f"seed{seed}_generations.csv"):
            assert ((directory / name).read_bytes()
                    == (out / "figure4" / "hopper" / "pgps" / name).read_bytes())


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_a_cell_with_a_checkpoint_of_the_generation_it_stopped_at(
        uninterrupted, tmp_path, sig):
    out, (result,) = uninterrupted
    directory = tmp_path / "cell"
    rarely = dataclasses.replace(BUDGET, checkpoint_every=None)  # none but the stop's

    def signal_at_third(generation, steps):
        if generation == 3:
            os.kill(os.getpid(), sig)
    handler = signal.getsignal(sig)
    with pytest.raises(KeyboardInterrupt):
        runner.run_cell(HOPPER, directory, rarely, signal_at_third)
    assert signal.getsignal(sig) is handler  # the cell's own handler is gone
    checkpoints = Checkpoints(directory / runner.CHECKPOINTS)
    assert checkpoints.steps() == [3]
    checkpoints.close()
    assert len(read_csv(directory / "seed1_generations.csv")[1]) == 3
    assert not (directory / runner.RESULT).exists()
    generations = []
    resumed = runner.run_cell(HOPPER, directory, rarely,
                              lambda generation, steps: generations.append(generation))
    assert generations[0] == 4
    assert _timeless(resumed) == _timeless(result)


def test_a_seed_running_in_another_process_is_refused_and_its_lock_goes_with_it(
        uninterrupted, tmp_path):
    """A seed's lock held by another process (here by this one, as another would hold it)
    refuses a command given that seed, the whole cell included, naming the holder; the locks
    it took go with it, and a cell that ran leaves none behind."""
    out, _ = uninterrupted
    assert not list((out / "figure4" / "hopper" / "pgps").glob("*.lock"))
    directory = tmp_path / "cell"
    directory.mkdir()
    held = rundir.RunLock(directory / runner.seed_lock(2))
    try:
        with pytest.raises(UsageError, match=f"{re.escape(str(directory))} is in use by "
                                             f"process {os.getpid()} on .*; seed 2 runs "
                                             "there; wait for it to finish or stop it, or "
                                             "give another --out"):
            runner.run_cell(HOPPER, directory, BUDGET)
    finally:
        held.release()
    assert [p.name for p in directory.iterdir()] == ["running_seed2.lock"]


def test_a_lock_file_removed_by_its_holder_as_it_is_locked_is_locked_again_at_its_path(
        tmp_path, monkeypatch):
    """The holder's `release(remove=True)` deletes the file it holds: a process that opened it
    just before then locks a file gone from the path, and must lock the one now there."""
    path = tmp_path / "running_seed1.lock"
    flock, holder_left = fcntl.flock, []

    def after_its_holder_left(file, operation):
        if not holder_left:  # the holder removes the file between this process's open and lock
            path.unlink()
            holder_left.append(True)
        return flock(file, operation)
    monkeypatch.setattr(fcntl, "flock", after_its_holder_left)
    lock = rundir.RunLock(path)
    monkeypatch.setattr(fcntl, "flock", flock)
    assert os.fstat(lock._file.fileno()).st_ino == path.stat().st_ino
    assert path.read_text().startswith(f"process {os.getpid()} on ")
    with pytest.raises(UsageError, match="is in use by process"):
        rundir.RunLock(path)
    lock.release(remove=True)
    assert not path.exists()


def test_sigterm_while_the_programs_compile_stops_the_command_as_ctrl_c_does(tmp_path, cache):
    """Before the cell's loop (which checkpoints on a signal) SIGTERM is Ctrl-C: the command
    says how to continue and leaves neither checkpoints nor its lock."""
    command_line = [sys.executable, "-m", "pgps_jax.experiments.paper", "figure4", "--tasks",
                    "hopper", "--configs", "pgps", "--seeds", "1", "--no-progress",
                    "--out", str(tmp_path)]
    process = subprocess.Popen(command_line, cwd=REPO, env=cli_env(cache), text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    lock = tmp_path / "figure4" / "hopper" / "pgps" / runner.seed_lock(1)
    wait_until(lambda: lock.exists() and lock.read_text().endswith("\n"), process, poll=0.01)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr[-2000:]
    assert "interrupted; the same command continues each cell" in stderr
    assert "Traceback" not in stderr
    assert list(lock.parent.iterdir()) == []


def test_checkpoints_follow_the_clock_where_no_generations_are_given(uninterrupted, tmp_path):
    """`Budget.checkpoint_every_s` alone: a checkpoint after every generation that ends that
    long after the last one (here: every generation), and the same result."""
    out, (result,) = uninterrupted
    directory = tmp_path / "cell"
    by_clock = dataclasses.replace(BUDGET, checkpoint_every=None, checkpoint_every_s=1e-9)
    latest = []

    def latest_checkpoint(generation, steps):
        written = [int(p.name) for p in (directory / runner.CHECKPOINTS).glob("*")
                   if p.name.isdigit()]
        latest.append(max(written, default=None))
    clocked = runner.run_cell(HOPPER, directory, by_clock, latest_checkpoint)
    assert latest == list(range(1, len(latest) + 1)) and len(latest) == result["generations"]
    assert _timeless(clocked) == _timeless(result)
    assert clocked["wall_split_s"]["checkpoints"] > 0


def test_a_signal_in_a_cell_s_last_generation_stops_after_its_result(uninterrupted,
                                                                      tmp_path):
    out, (result,) = uninterrupted

    def signal_at_budget(generation, steps):
        if steps.min() >= BUDGET.steps:
            os.kill(os.getpid(), signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):  # the command runs no further cell
        runner.run_cell(HOPPER, tmp_path / "cell", BUDGET, signal_at_budget)
    done = json.loads((tmp_path / "cell" / runner.RESULT).read_text())
    assert _timeless(done) == _timeless(result)


def test_a_done_cell_given_more_seeds_runs_only_those(uninterrupted, tmp_path):
    out, (result,) = uninterrupted
    cell = tmp_path / "figure4" / "hopper" / "pgps"
    shutil.copytree(out / "figure4" / "hopper" / "pgps", cell)
    before = {p.name: p.read_bytes() for p in cell.iterdir() if p.name != runner.RESULT}
    three = dataclasses.replace(BUDGET, seeds=3)
    with pytest.raises(UsageError, match="done with 2 seeds"):
        runner.run_cell(HOPPER, cell, three)  # all three in one program: not over seeds done
    curves, _, _ = report._ours(cell)
    (cell / "seed3.csv").write_bytes(b",Step,Mean,Std,Reward1,Reward2\n0,200,1.0,0.0,1.0,1.0\n")
    drawn = report._ours(cell)[0]  # a seed under way is not drawn with the done ones
    assert drawn.returns.shape == curves.returns.shape == (2, len(curves.steps))
    np.testing.assert_array_equal(drawn.returns, curves.returns)
    older = json.loads((cell / runner.RESULT).read_text())  # a result from before wall_split_s
    del older["wall_split_s"]
    older["device"] = "1 × an older card"  # the seeds done ran elsewhere
    (cell / runner.RESULT).write_text(json.dumps(older))
    (merged,) = command.run("figure4", tmp_path, three, tasks=["hopper"], configs=["pgps"],
                            progress=False)
    assert merged["seeds"] == [1, 2, 3] and merged["settings"]["seeds"] == 3
    assert "wall_split_s" not in merged and "wall_split_s" not in merged["parts"][0]
    assert [part["seeds"] for part in merged["parts"]] == [[1, 2], [3]]
    assert [part["device"] for part in merged["parts"]] == ["1 × an older card", result["device"]]
    assert merged["device"] == f"1 × an older card; {result['device']}"
    assert {actor: values[:2] for actor, values in merged["final"].items()} == result["final"]
    assert all((cell / name).read_bytes() == content for name, content in before.items())
    # seed 3 is what it is as the second part of a cell of three run two seeds to a program
    alone = runner.run_cell(HOPPER, tmp_path / "in_parts", dataclasses.replace(
        three, seeds_per_program=2), part=runner.Seeds(3, 1, whole=False))
    assert alone["env_steps"] == merged["env_steps"][2:]
    assert alone["final"] == {actor: values[2:] for actor, values in merged["final"].items()}
    again = command.run("figure4", tmp_path, three, tasks=["hopper"], configs=["pgps"],
                        progress=False)
    assert again == [merged]


def test_parts_give_a_done_cell_its_further_seeds():
    ten = dataclasses.replace(BUDGET, seeds=10)
    assert runner.parts(ten, done=5) == [runner.Seeds(1, 5, whole=True),
                                         runner.Seeds(6, 5, whole=False)]
    assert runner.parts(dataclasses.replace(ten, seeds_per_program=2), done=5) == [
        runner.Seeds(1, 5, whole=True), runner.Seeds(6, 2, whole=False),
        runner.Seeds(8, 2, whole=False), runner.Seeds(10, 1, whole=False)]
    assert runner.parts(ten, done=10) == runner.parts(ten, done=12) == [runner.whole_cell(ten)]
    assert runner.parts(ten) == [runner.whole_cell(ten)]


IN_PARTS = dataclasses.replace(BUDGET, seeds_per_program=1)


def _cut_off_after_generation_3(cell: pathlib.Path, part: runner.Seeds) -> None:
    """Runs `part` of the hopper cell in `cell` until it is cut off after its third
    generation, its files written after every generation (its checkpoint after the second)."""
    def cut_off(generation, steps):
        if generation == 3:
            raise Stop
    every, runner.FILES_EVERY_S = runner.FILES_EVERY_S, 0.0
    try:
        with pytest.raises(Stop):
            runner.run_cell(HOPPER, cell, IN_PARTS, cut_off, part)
    finally:
        runner.FILES_EVERY_S = every


@pytest.fixture(scope="module")
def in_parts(tmp_path_factory):
    """The cell's seeds in programs of one seed each, in turn; the second part cut off after
    its third generation (its files written after every generation, the checkpoint after
    the second) and continued from its checkpoint."""
    out = tmp_path_factory.mktemp("paper_in_parts")
    cell = out / "figure4" / "hopper" / "pgps"
    _cut_off_after_generation_3(cell, runner.parts(IN_PARTS)[1])
    assert (cell / "checkpoints_seeds2-2").is_dir() and not (cell / runner.RESULT).exists()
    for name in ("seed2_generations.csv", "generation_times_seeds2-2.csv"):
        assert len(read_csv(cell / name)[1]) == 3, name  # past the checkpoint's two
    with pytest.raises(UsageError, match="run in parts .*checkpoints_seeds2-2.*seeds-per-program"):
        runner.run_cell(HOPPER, cell, BUDGET)  # the cell whole: the part continues in parts
    first = runner.run_cell(HOPPER, cell, IN_PARTS, part=runner.parts(IN_PARTS)[0])
    assert first["seeds"] == [1] and not (cell / runner.RESULT).exists()
    generations = []
    runner.run_cell(HOPPER, cell, IN_PARTS, lambda generation, steps: generations.append(
        generation), runner.parts(IN_PARTS)[1])
    assert generations[0] == 3  # from the checkpoint of generation 2
    (result,) = command.run("figure4", out, IN_PARTS, tasks=["hopper"], configs=["pgps"],
                            progress=False)
    return out, result


def test_a_cell_in_parts_keys_its_seeds_as_the_whole_cell_and_merges_their_results(
        uninterrupted, in_parts):
    """Each part runs its own seeds under the whole cell's keys (seed k's first evaluation,
    of μ before any learning, is the whole cell's to float tolerance), writes their files
    and its result, and the cell's result merges the parts'."""
    assert runner.parts(IN_PARTS) == [runner.Seeds(1, 1, whole=False),
                                      runner.Seeds(2, 1, whole=False)]
    assert [p.suffix for p in runner.parts(dataclasses.replace(BUDGET, seeds=5,
                                                               seeds_per_program=2))] == [
        "_seeds1-2", "_seeds3-4", "_seeds5-5"]
    assert runner.parts(dataclasses.replace(BUDGET, seeds_per_program=2)) == [
        runner.Seeds(1, 2, whole=True)]
    (whole_out, _), (out, result) = uninterrupted, in_parts
    cell, whole = (o / "figure4" / "hopper" / "pgps" for o in (out, whole_out))
    assert result["seeds"] == [1, 2] and [p["seeds"] for p in result["parts"]] == [[1], [2]]
    assert result["wall_s"] == pytest.approx(sum(p["wall_s"] for p in result["parts"]))
    for key in runner.WALL_SPLIT:
        assert result["wall_split_s"][key] == pytest.approx(
            sum(p["wall_split_s"][key] for p in result["parts"]))
    assert min(result["env_steps"]) >= BUDGET.steps
    firsts = []
    for seed in (1, 2):
        part = json.loads((cell / f"result_seeds{seed}-{seed}.json").read_text())
        assert part["seeds"] == [seed]
        assert part["final"]["mu"] == [result["final"]["mu"][seed - 1]]
        _, rows = read_csv(cell / runner.seed_file(seed))
        _, whole_rows = read_csv(whole / runner.seed_file(seed))
        first = [float(rows[0][f"Reward{i}"]) for i in (1, 2)]
        np.testing.assert_allclose(first, [float(whole_rows[0][f"Reward{i}"]) for i in (1, 2)],
                                   rtol=1e-4)
        firsts.append(first)
    assert firsts[0] != firsts[1]
    assert not list(cell.glob("checkpoints*")) and not list(cell.glob("at_budget*"))
    assert sorted(p.name for p in cell.glob("generation_times*")) == [
        "generation_times_seeds1-1.csv", "generation_times_seeds2-2.csv"]
    stale = dataclasses.replace(IN_PARTS, steps=BUDGET.steps + 200)
    with pytest.raises(UsageError, match=r"(?s)other settings.*steps: 600 there, 800 now"):
        runner.merge_parts(cell, stale, runner._settings(
            "pgps", for_task("hopper", **TINY), stale, 1, make_env("hopper")), "hopper")


def test_a_part_whose_checkpoint_was_lost_runs_again_from_its_start(in_parts, tmp_path):
    """A part cut off together with its machine leaves its curves, but no checkpoint, where
    its results were copied: it runs again from its first generation,
    its stale files replaced, to the part's uninterrupted result; a done part beside it is
    kept as it is."""
    out, _ = in_parts
    done = out / "figure4" / "hopper" / "pgps"
    cell = tmp_path / "cell"
    cell.mkdir()
    shutil.copy(done / "result_seeds2-2.json", cell)
    first = runner.parts(IN_PARTS)[0]
    _cut_off_after_generation_3(cell, first)
    shutil.rmtree(cell / "checkpoints_seeds1-1")  # the part's checkpoint lost with its cut-off
    stale = (cell / "seed1_generations.csv").read_bytes()
    generations = []
    result = runner.run_cell(HOPPER, cell, IN_PARTS,
                             lambda generation, steps: generations.append(generation), first)
    assert generations[0] == 1
    assert _timeless(result) == _timeless(json.loads((done / "result_seeds1-1.json").read_text()))
    for name in (runner.seed_file(1), runner.seed_file(1, "td3"), "seed1_generations.csv"):
        assert (cell / name).read_bytes() == (done / name).read_bytes(), name
    assert (cell / "seed1_generations.csv").read_bytes() != stale
    assert json.loads((cell / runner.RESULT).read_text())["seeds"] == [1, 2]  # merged


def test_a_part_stopped_before_its_first_checkpoint_leaves_neither_checkpoints_nor_records(
        in_parts, tmp_path):
    """Stopped in its first generation (before any checkpoint), a part leaves no checkpoints
    folder, which would hold the cell to its split; and a fresh start drops the at-budget
    record of an earlier run, whose seeds' records it would otherwise take for its own."""
    cell = tmp_path / "cell"
    cell.mkdir()
    first = runner.parts(IN_PARTS)[0]
    earlier = cell / runner.part_file(runner.AT_BUDGET, first)
    earlier.write_bytes(b"an earlier run's record")

    def stop(generation, steps):
        raise Stop
    with pytest.raises(Stop):
        runner.run_cell(HOPPER, cell, IN_PARTS, stop, first)
    assert not (cell / runner.part_file(runner.CHECKPOINTS, first)).exists()
    assert not earlier.exists()


def test_done_parts_and_checkpoints_of_another_split_are_refused(tmp_path):
    """A cell continues only in the split it was started in: a done part of another split
    (whose seeds it would play again, over their files) is refused as another split's
    checkpoints are, unless the cell's result holds its seeds already; an empty checkpoints
    folder holds no checkpoint. A checkpoint of other devices is refused with how to
    continue it, not with removing the cell's folder."""
    four = dataclasses.replace(BUDGET, seeds=4, seeds_per_program=2)
    settings = runner._settings("pgps", for_task("hopper", **TINY), four, 1, make_env("hopper"))
    (tmp_path / "result_seeds1-2.json").write_text(json.dumps({"seeds": [1, 2],
                                                               "settings": settings}))
    runner._require_parts_alike(tmp_path, four, settings, "hopper")  # its own split
    one = dataclasses.replace(four, seeds_per_program=1)
    with pytest.raises(UsageError, match=r"done in another split \(result_seeds1-2.json\)"):
        runner._require_parts_alike(tmp_path, one, settings, "hopper")
    (tmp_path / runner.RESULT).write_text(json.dumps({"seeds": [1, 2], "settings": settings}))
    runner._require_parts_alike(tmp_path, one, settings, "hopper")  # merged: seeds 3-4 given
    (tmp_path / "checkpoints_seeds3-4").mkdir()  # a part of two stopped while compiling
    runner._require_parts_alike(tmp_path, one, settings, "hopper")
    (tmp_path / "checkpoints_seeds3-4" / "5").mkdir()
    with pytest.raises(UsageError, match=r"run in parts \(checkpoints_seeds3-4\)"):
        runner._require_parts_alike(tmp_path, one, settings, "hopper")
    elsewhere = {**settings, "devices": 2}
    with pytest.raises(UsageError, match=r"(?s)continue it with the settings, --seeds and "
                                         r"devices.*devices: 2 there, 1 now"):
        runner._require_same(tmp_path, elsewhere, settings, "hopper")
    runner._require_same(tmp_path, elsewhere, settings, "hopper", done=True)


def test_a_failing_summary_leaves_the_run_s_own_error_reported(tmp_path, monkeypatch, capsys):
    done = tmp_path / "figure4" / "hopper" / "pgps"
    done.mkdir(parents=True)
    (done / runner.RESULT).write_text("{}")

    def failing_cell(*args):
        raise RunFailed("hopper pgps: a program failed")

    def failing_summary(*args):
        raise ValueError("no figure")
    monkeypatch.setattr(command, "_run_in_turn", failing_cell)
    monkeypatch.setattr(command, "write_summary", failing_summary)
    with pytest.raises(RunFailed, match="a program failed"):
        command.run("figure4", tmp_path, BUDGET, tasks=["hopper"], configs=["pgps"],
                    progress=False)
    assert "were not drawn: no figure" in capsys.readouterr().err


def _same_platform(cache: pathlib.Path) -> dict:
    """A child command's environment: a CLI subprocess's (`cli_env`) on this test's platform,
    so that its cells compute what this process's in-turn cells computed."""
    return {**cli_env(cache), "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS", "")}


def test_cells_side_by_side_compute_what_they_compute_in_turn(in_parts, tmp_path, cache):
    """Programs in processes of their own, two at a time (the two parts of one cell, then a
    cell that fails): the parts give the results of the in-turn run, byte for byte, its
    cut-off part included; the cell that fails is named, after the others have finished."""
    out, result = in_parts
    refused = tmp_path / "figure4" / "hopper" / "cemrl"
    refused.mkdir(parents=True)
    (refused / runner.RESULT).write_bytes(  # a result of another cell
        (out / "figure4" / "hopper" / "pgps" / runner.RESULT).read_bytes())
    with pytest.raises(RunFailed, match=r"1 of 3 program\(s\) failed: hopper cemrl: .* other "
                                        "settings"):
        command.run("figure4", tmp_path, IN_PARTS, tasks=["hopper"], configs=["pgps", "cemrl"],
                    progress=False, concurrent=2, child_environ=_same_platform(cache))
    _, rows = read_csv(tmp_path / "figure4" / command.FINAL_RETURNS)  # written all the same
    assert [(r["config"], r["seed"]) for r in rows] == [("pgps", "1"), ("pgps", "2")] * 2
    cell = tmp_path / "figure4" / "hopper" / "pgps"
    beside = json.loads((cell / runner.RESULT).read_text())
    if jax.device_count() > 1 or jax.default_backend() != "cpu":
        # a child sees one GPU, and GPU kernels need not repeat bit for bit across processes
        assert beside["seeds"] == result["seeds"] and np.all(np.isfinite(beside["final"]["mu"]))
        return
    assert _timeless(beside) == _timeless(result)
    for seed in (1, 2):
        for name in (runner.seed_file(seed), runner.seed_file(seed, "td3"),
                     f"seed{seed}_generations.csv"):
            assert ((cell / name).read_bytes()
                    == (out / "figure4" / "hopper" / "pgps" / name).read_bytes())


def test_the_grid_benchmark_times_a_cell_run_in_parts(in_parts, tmp_path, cache):
    """`benchmarks.grid_throughput grid --seeds-per-program 1`: the cell's two seeds run as two
    programs side by side, which compute what the in-turn parts compute; the entry records
    the split, each part's wall-clock, the cell's the sum of its parts', and the XLA flags it
    ran under."""
    out, result = in_parts
    results = tmp_path / "grid_throughput.json"
    env = _same_platform(cache)
    # the tests' flags, under which the parts' programs load from the compilation cache
    assert env["XLA_FLAGS"]
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.grid_throughput", "grid", "--smoke", "--tasks",
         "hopper", "--grid-seeds", "2", "--seeds-per-program", "1", "--concurrent", "2",
         "--out", str(tmp_path / "grid"), "--results", str(results)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    [entry] = json.loads(results.read_text())
    assert entry["xla_flags"] == env["XLA_FLAGS"]
    assert (entry["kind"], entry["seeds"], entry["seeds_per_program"], entry["concurrent"]) == (
        "grid", 2, 1, 2)
    [cell] = entry["cells"]
    assert len(cell["parts_wall_s"]) == 2 and min(cell["parts_wall_s"]) > 0
    assert cell["wall_s"] == pytest.approx(sum(cell["parts_wall_s"]))
    timed = json.loads((tmp_path / "grid" / "figure4" / "hopper" / "pgps" / runner.RESULT)
                       .read_text())
    assert [p["seeds"] for p in timed["parts"]] == [[1], [2]]
    if jax.device_count() == 1 and jax.default_backend() == "cpu":
        assert (timed["final"], timed["env_steps"]) == (result["final"], result["env_steps"])
        assert cell["final_mu"] == result["final"]["mu"]


def test_importing_the_commands_starts_no_jax_backend():
    """The side-by-side command's own process leaves the GPUs' memory to its cells: nothing
    it imports makes a device array (a GPU backend, once started, preallocates its memory)."""
    code = ("import pgps_jax.experiments.paper.command, pgps_jax.train, pgps_jax.evaluate, "
            "benchmarks.grid_throughput; from jax._src import xla_bridge; "
            "print(xla_bridge.backends_are_initialized())")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                            text=True, timeout=300)
    assert result.stdout.strip() == "False", result.stderr[-2000:]


def test_slots_are_placed_on_the_gpus_in_turn():
    five = side_by_side.placements(5, "gpu", 2, None)
    assert [p["CUDA_VISIBLE_DEVICES"] for p in five] == ["0", "1", "0", "1", "0"]
    assert {p[side_by_side.MEMORY_FRACTION] for p in five} == {"0.300"}
    assert [p["CUDA_VISIBLE_DEVICES"] for p in side_by_side.placements(3, "gpu", 2, "4,6")] == [
        "4", "6", "4"]
    assert side_by_side.placements(2, "cpu", 1, None) == [{}, {}]


def test_slots_divide_the_commands_own_share_of_a_gpu():
    """A command given a memory fraction of its own (to leave room for other processes on the
    GPU) divides that among its slots, under either of JAX's names; a bad one is refused."""
    assert side_by_side.memory_share({}) == side_by_side.MEMORY_IN_USE
    assert side_by_side.memory_share({"XLA_CLIENT_MEM_FRACTION": "0.6"}) == 0.6
    assert side_by_side.memory_share({"XLA_PYTHON_CLIENT_MEM_FRACTION": "0.45"}) == 0.45
    three = side_by_side.placements(3, "gpu", 1, None, memory=0.6)
    assert [p[side_by_side.MEMORY_FRACTION] for p in three] == ["0.200"] * 3
    for bad in ("0", "1.5", "half"):
        with pytest.raises(UsageError, match=r"XLA_CLIENT_MEM_FRACTION.*\(0, 1\]"):
            side_by_side.memory_share({"XLA_CLIENT_MEM_FRACTION": bad})


def test_seeds_are_split_over_the_devices(tmp_path):
    """Three seeds on two (host) devices: a batch of four, the fourth dropped."""
    env = {**os.environ, "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")
           + " --xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    sets = [f"{k}={list(v) if isinstance(v, tuple) else v}" for k, v in TINY.items()]
    result = subprocess.run(
        [sys.executable, "-m", "pgps_jax.experiments.paper", "figure4", "--tasks", "hopper",
         "--configs", "pgps", "--steps", "400", "--seeds", "3", "--no-progress", "--set", *sets, "--eval",
         "every=200", "episodes=2", "steps=50", "--out", str(tmp_path)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    cell = json.loads((tmp_path / "figure4" / "hopper" / "pgps" / runner.RESULT).read_text())
    assert cell["device"].startswith("2 × ") and cell["seeds"] == [1, 2, 3]
    assert len(cell["final"]["mu"]) == 3 and np.all(np.isfinite(cell["final"]["mu"]))
    mu = cell["final"]["mu"]  # the command's closing line for the cell
    assert (f"figure4 hopper pgps: seeds 1, 2, 3 done at {min(cell['env_steps']):,} env steps "
            f"or more; final mu {np.mean(mu):,.1f} ± {np.std(mu, ddof=1):,.1f}") in result.stdout
    assert sorted(p.name for p in (tmp_path / "figure4" / "hopper" / "pgps").glob("*.csv")) == [
        runner.GENERATION_TIMES] + [f"seed{k}{kind}.csv" for k in (1, 2, 3)
                                    for kind in ("", "_elite", "_generations", "_td3")]


def test_padding_rounds_the_batch_up_to_the_devices():
    assert [runner.padded_seeds(s, 2) for s in (1, 2, 3, 5)] == [2, 2, 4, 6]
    assert runner.padded_seeds(5, 1) == 5


def test_the_grids_hold_the_paper_s_cells():
    assert [(c.task, c.config, c.algo) for c in grid.cells("figure4")] == [
        (task, algo, algo) for task in ("swimmer", "halfcheetah", "hopper", "walker2d", "ant")
        for algo in ("pgps", "cem", "td3", "cemrl")]
    table1 = grid.cells("table1", tasks=("ant",))
    assert [c.config for c in table1] == ["base", "pg_to_ea", "ea_to_pg", "q_filter", "pgps"]
    flags = ("pg_guides_ea", "ea_guides_pg", "q_filter", "increasing_steps")
    switched_on = [sum(dict(c.overrides).get(f, True) for f in flags) for c in table1]
    assert switched_on == [0, 1, 2, 3, 4]  # each model adds one coupling to the one before
    ordered = grid.cells("figure4", tasks=("ant", "swimmer"), configs=("pgps", "td3"))
    assert [(c.task, c.config) for c in ordered] == [  # the cells start in the tasks' order
        ("ant", "pgps"), ("ant", "td3"), ("swimmer", "pgps"), ("swimmer", "td3")]


@pytest.mark.parametrize("args, words", [
    (["figure7"], ["unknown experiment 'figure7'", "figure4", "table1"]),
    (["figure7", "--report"], ["unknown experiment 'figure7'", "figure4", "table1"]),
    (["figure4", "--report", "--reference", "nowhere"], ["--reference nowhere: no such folder"]),
    (["table1", "--tasks", "swimmer"], ["table1 has no task swimmer", "ant", "walker2d"]),
    (["figure4", "--configs", "sac"], ["no configuration sac", "cem, cemrl, pgps, td3"]),
    (["figure4", "--configs", "cem", "--set", "warmup_steps=200"],
     ["swimmer cem: CEM alone has no replay buffer to warm up"]),
    (["figure4", "--set", "pop_sise=4"], ["--set 'pop_sise=4'", "pop_size"]),
    (["figure4", "--set", "q_filter=maybe"], ["--set q_filter must be true or false"]),
    (["table1", "--set", "q_filter=true"], ["--set q_filter", "sets it itself"]),
    (["figure4", "--configs", "td3", "--set", "increasing_steps=false"],
     ["--set increasing_steps: PGPS's couplings", "swimmer td3 has none", "--configs pgps"]),
    (["figure4", "--steps", "5000"], ["--steps 5000 does not exceed the random warm-up"]),
    (["figure4", "--set", "top_k=99"], ["top_k=99", "pop_size"]),
    (["figure4", "--eval", "often=3"], ["--eval 'often=3'", "every, episodes, steps"]),
    (["figure4", "--set", "top_k=3", "--set", "pop_size=2"],  # repeated options add up
     ["top_k=3 is invalid: must be in [1, pop_size=2]"]),
    (["figure4", "--eval", "every=0", "--eval", "episodes=2", "--set", "top_k=99"],
     ["EvaluationConfig.every=0 is invalid"]),
    (["figure4", "--steps", "0"], ["--steps must be a positive integer"]),
    (["figure4", "--concurrent", "0"], ["--concurrent must be a positive integer"]),
    (["figure4", "--seeds-per-program", "0"], ["--seeds-per-program must be a positive integer"]),
    (["figure4", "--checkpoint-every", "0"], ["--checkpoint-every must be a positive integer"]),
    (["figure4", "--checkpoint-every-s", "0"],
     ["--checkpoint-every-s must be a positive number of seconds"]),
    (["figure4", "--checkpoint-every-s", "inf"],
     ["--checkpoint-every-s must be a positive number of seconds, finite, got inf"]),
    (["figure4", "--env", "contacts=all"], ["--env 'contacts=all'", "floor_contacts"]),
    (["figure4", "--tasks", "ant", "--env", "floor_contacts=all"],
     ["--env: floor_contacts must be one of model, gym, got 'all'"]),
])
def test_bad_input_is_one_message_and_status_2(tmp_path, args, words):
    result = run_here("experiments.paper.command", [*args, "--out", str(tmp_path)], tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    for word in words:
        assert word in result.stderr
    assert "Traceback" not in result.stderr and result.stderr.count("error:") == 1
    assert list(tmp_path.iterdir()) == []

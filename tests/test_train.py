"""`python -m pgps_jax.train` end to end on a tiny run: every output file and its columns,
re-evaluation, bad inputs (message, non-zero exit, nothing half-written) and a NaN stop."""

import json
import pathlib
import shutil
import weakref

import imageio.v3 as iio
import jax.numpy as jnp
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pgps_jax.cli import loop, train
from pgps_jax.cli.errors import EXIT_FAILED
from pgps_jax.agent import metrics as schema
from pgps_jax.cli import run_dir as rundir
from pgps_jax.agent.pgps import PGPS
from pgps_jax.cli.run_config import CONFIG_DIR, from_dict

from train_cli import (checkpoint_steps, leftovers, read_csv, run, run_here, tensorboard_tags,
                       tiny)

TOTAL, EVAL_EVERY, WARMUP, POP = 3000, 400, 200, 4

pytestmark = pytest.mark.xdist_group("train_point")  # one worker makes the reference run


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted tiny run with the progress bar on (in this process: the tests' later
    runs of its settings reuse its compiled programs)."""
    work = tmp_path_factory.mktemp("work")
    run_dir = work / "ref"
    result = run_here("train", tiny("progress=true", f"run_dir={run_dir}"), work)
    assert result.returncode == 0, result.stderr[-3000:]
    return run_dir, result


def test_progress_bar_and_summary(reference):
    _, result = reference
    assert "step/s" in result.stderr and "eval" in result.stderr  # tqdm: rate, ETA, last eval
    assert f"/{TOTAL / 1000:.2f}k" in result.stderr or f"/{TOTAL}" in result.stderr
    assert "done:" in result.stdout and "final μ return" in result.stdout


def test_run_directory_holds_every_output(reference):
    run_dir, _ = reference
    for name in (rundir.CONFIG, rundir.METRICS, rundir.EVAL, rundir.EVAL_POLICIES, rundir.CURVE,
                 rundir.ACTORS, rundir.TENSORBOARD, rundir.CHECKPOINTS):
        assert (run_dir / name).exists(), name
    assert leftovers(run_dir) == []


def test_resolved_config_is_saved(reference):
    run_dir, _ = reference
    settings, config = from_dict(rundir.RunDir(run_dir).read_config())
    assert (settings.env, settings.seed, settings.total_steps) == ("point", 1, TOTAL)
    assert (config.pop_size, config.actor_hidden, config.warmup_steps) == (POP, (32, 32), WARMUP)


def test_metrics_csv_has_one_row_per_generation(reference):
    run_dir, _ = reference
    header, rows = read_csv(run_dir / rundir.METRICS)
    assert header == rundir.metrics_columns(schema.generation_metrics(POP))
    for column in ("env_steps", "T", "return_0", "return_3", "elite_return", "td3_return",
                   "guided_loss", "beta", "critic_loss", "actor_loss", "steps_per_s"):
        assert column in header
    assert [int(r["generation"]) for r in rows] == list(range(1, len(rows) + 1))
    steps = [int(r["env_steps"]) for r in rows]
    assert steps == sorted(steps) and steps[-1] >= TOTAL > steps[-2]
    assert all(20 <= int(r["T"]) <= 50 for r in rows)
    assert all(r["guided_loss"] in ("0", "1") for r in rows)
    assert all(np.isfinite(float(r["critic_loss"])) and float(r["steps_per_s"]) > 0 for r in rows)
    elite = [float(r["elite_return"]) for r in rows]
    best = [max(float(r[f"return_{i}"]) for i in range(POP)) for r in rows]
    assert elite == best


def test_eval_csv_is_in_the_reference_format(reference):
    run_dir, _ = reference
    header, rows = read_csv(run_dir / rundir.EVAL)
    assert header == ["", "Step", "Mean", "Std"] + [f"Reward{i}" for i in range(1, 11)]
    assert [int(r[""]) for r in rows] == list(range(len(rows)))
    # at the start (after the warm-up), at each crossing of a multiple of eval_every, at the end
    _, metrics = read_csv(run_dir / rundir.METRICS)
    steps = [WARMUP] + [int(r["env_steps"]) for r in metrics]
    expected = [WARMUP] + [s for p, s in zip(steps, steps[1:]) if s // EVAL_EVERY > p // EVAL_EVERY]
    if expected[-1] != steps[-1]:
        expected.append(steps[-1])
    assert [int(r["Step"]) for r in rows] == expected
    for r in rows:
        rewards = np.array([float(r[f"Reward{i}"]) for i in range(1, 11)])
        assert float(r["Mean"]) == pytest.approx(rewards.mean(), rel=1e-5, abs=1e-5)
        assert float(r["Std"]) == pytest.approx(rewards.std(), rel=1e-4, abs=1e-5)
    _, policies = read_csv(run_dir / rundir.EVAL_POLICIES)
    assert [p["Step"] for p in policies] == [r["Step"] for r in rows]
    assert [p["mu_mean"] for p in policies] == [r["Mean"] for r in rows]


def test_tensorboard_curve_actor_and_checkpoints(reference):
    run_dir, _ = reference
    tags = tensorboard_tags(run_dir / rundir.TENSORBOARD)
    assert {"eval/mu_mean", "eval/td3_mean", "td3/critic_loss", "td3/actor_loss", "td3/beta",
            "pop/return_mean", "perf/steps_per_s"} <= tags
    image = iio.imread(run_dir / rundir.CURVE)
    assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0
    _, metrics = read_csv(run_dir / rundir.METRICS)
    last = int(metrics[-1]["generation"])
    actors = rundir.load_actors(run_dir / rundir.ACTORS)
    assert actors["generation"] == last and actors["env_steps"] == int(metrics[-1]["env_steps"])
    n_params = (4 * 32 + 32) + (32 * 32 + 32) + (32 * 2 + 2)
    assert actors["mu"].shape == actors["td3"].shape == actors["elite"].shape == (n_params,)
    steps = checkpoint_steps(run_dir)
    assert len(steps) == 3 and steps[-1] == last  # the last 3, the final one included


def test_evaluate_reproduces_the_last_evaluation(reference, cache, tmp_path):
    run_dir, _ = reference
    out = tmp_path / "re.csv"
    result = run("evaluate", [f"run={run_dir}", f"out={out}"], cache, tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "mu" in result.stdout and "td3" in result.stdout and "elite" in result.stdout
    _, rows = read_csv(out)
    _, training = read_csv(run_dir / rundir.EVAL)
    strip = lambda r: {k: v for k, v in r.items() if k != ""}
    assert strip(rows[0]) == strip(training[-1])


@pytest.mark.parametrize("args, words", [
    (["out=missing/re.csv"], ["out=missing/re.csv: cannot write there", "No such file"]),
    (["steps=0"], ["steps=0 is invalid: must be an integer >= 1"]),
    (["out="], ["out=: name a file to write, not a folder"]),
    (["episodes=0"], ["episodes=0 is invalid: must be an integer >= 1"]),
    (["seed=-5"], ["seed=-5 is invalid: must be an integer >= 0"]),
    (["length=5"], ["unknown argument 'length=5'", "steps=..."]),
])
def test_evaluate_refuses_bad_arguments_before_playing(reference, tmp_path, args, words):
    run_dir, _ = reference
    result = run_here("evaluate", [f"run={run_dir}", *args], tmp_path)
    assert result.returncode == 2
    for word in words:
        assert word in result.stderr
    assert result.stdout == "" and "Traceback" not in result.stderr  # nothing was played


@pytest.mark.parametrize("text, words", [
    ("env: [point\n", ["is not valid YAML"]),
    ("", ["holds no settings"]),
])
def test_evaluate_names_a_damaged_config_file(reference, tmp_path, text, words):
    run_dir, _ = reference
    copy = tmp_path / "damaged"
    shutil.copytree(run_dir, copy)
    (copy / rundir.CONFIG).write_text(text)
    result = run_here("evaluate", [f"run={copy}"], tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert str(copy / rundir.CONFIG) in result.stderr
    for word in words:
        assert word in result.stderr


def test_evaluate_plays_episodes_of_the_steps_asked_for(reference, tmp_path):
    run_dir, _ = reference
    short, full = (run_here("evaluate", [f"run={run_dir}", *args, "episodes=3"], tmp_path)
                   for args in (["steps=7"], []))
    assert short.returncode == 0 and full.returncode == 0, short.stderr[-2000:]
    assert "3 episodes of 7 steps" in short.stdout and "3 episodes of 50 steps" in full.stdout
    mu = lambda result: [line for line in result.stdout.splitlines() if "mu" in line][0]
    assert mu(short) != mu(full)  # the returns of 7 steps, not of the run's 50


@pytest.mark.parametrize("command", ["evaluate", "render"])
def test_the_tools_print_their_usage_on_help(command, tmp_path):
    result = run_here(command, ["--help"], tmp_path)
    assert result.returncode == 0 and result.stderr == ""
    assert f"python -m pgps_jax.{command} run=<dir>" in result.stdout
    assert "Arguments (key=value)" in result.stdout


def test_render_refuses_a_task_without_a_mujoco_model(reference, tmp_path):
    run_dir, _ = reference
    result = run_here("render", [f"run={run_dir}", f"out={tmp_path / 'x.gif'}"], tmp_path)
    assert result.returncode == 2
    assert "no MuJoCo model" in result.stderr and not (tmp_path / "x.gif").exists()


@pytest.mark.parametrize("args, words", [
    (["env=humanoid"], ["unknown env 'humanoid'", "halfcheetah", "hopper", "walker2d", "ant",
                        "swimmer"]),
    (["pgps.foo=1"], ["'pgps.foo'", "pop_size"]),
    (["learning_rate=1"], ["'learning_rate'", "total_steps"]),
    (["pgps.top_k=99"], ["top_k=99", "pop_size"]),
    (["pgps.q_filter=maybe"], ["pgps.q_filter", "true or false"]),
    (["resume=true", "pgps.top_k=99"], ["top_k=99", "pop_size"]),
    (["resume=true", "pgps.q_filter=maybe"], ["pgps.q_filter", "true or false"]),
])
def test_bad_settings_fail_before_anything_is_written(args, words, tmp_path):
    run_dir = tmp_path / "run"
    result = run_here("train", tiny(f"run_dir={run_dir}", *args), tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    for word in words:
        assert word in result.stderr
    assert "Traceback" not in result.stderr
    assert not run_dir.exists()


def test_unwritable_output_directory_fails_before_training(tmp_path):
    blocker = tmp_path / "not_a_directory"
    blocker.write_text("x")
    result = run_here("train", tiny(f"output_dir={blocker}"), tmp_path)
    assert result.returncode == 2
    assert "cannot write the run directory" in result.stderr and str(blocker) in result.stderr
    assert "Traceback" not in result.stderr


def _snapshot(run_dir: pathlib.Path) -> dict:
    """Every file's size and time, but the lock's (it names its latest holder)."""
    return {str(p.relative_to(run_dir)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in run_dir.rglob("*") if p.is_file() and p.name != rundir.LOCK}


@pytest.mark.parametrize("args, words", [
    ([], ["already holds a run", "resume=true"]),
    (["resume=true", "pgps.q_filter=false"], ["different configuration",
                                              "pgps.q_filter: checkpoint True, now False"]),
    (["resume=true", "seed=5", "eval_every=100"], ["seed: checkpoint 1, now 5",
                                                   "eval_every: checkpoint 400, now 100"]),
])
def test_an_existing_run_is_never_overwritten_or_resumed_with_other_settings(
        reference, tmp_path, args, words):
    run_dir, _ = reference
    before = _snapshot(run_dir)
    result = run_here("train", tiny(f"run_dir={run_dir}", *args), tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    for word in words:
        assert word in result.stderr
    assert _snapshot(run_dir) == before


def test_a_checkpoint_from_before_a_new_setting_resumes_under_its_default(reference,
                                                                          tmp_path):
    """A checkpoint written before PGPSConfig gained a field (its saved configuration lacks
    it) resumes with resume=true: the field takes its default, the behaviour from before."""
    run_dir, _ = reference
    older = tmp_path / "older"
    shutil.copytree(run_dir, older)
    for path in (older / rundir.CHECKPOINTS).glob("*/meta/metadata"):
        meta = json.loads(path.read_text())
        del meta["config"]["pgps"]["update_unroll"]
        path.write_text(json.dumps(meta))
    result = run_here("train", tiny(f"run_dir={older}", "resume=true"), tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "done:" in result.stdout


def test_a_checkpoint_from_before_the_clock_resumes_by_directory_on_generations(reference,
                                                                                 tmp_path):
    """A checkpoint whose configuration has no checkpoint_every_s (written before it) continues,
    by directory, as it was checkpointed: every checkpoint_every generations, not by the
    clock; `evaluate` reads such a run."""
    from pgps_jax.cli.plan import plan
    run_dir, _ = reference
    older = tmp_path / "older"
    shutil.copytree(run_dir, older)
    metas = list((older / rundir.CHECKPOINTS).glob("*/meta/metadata"))
    assert len(metas) == 3
    for path in metas:
        meta = json.loads(path.read_text())
        meta["config"].pop("checkpoint_every_s")
        path.write_text(json.dumps(meta))
    config = (older / rundir.CONFIG).read_text()
    (older / rundir.CONFIG).write_text(
        "\n".join(line for line in config.splitlines() if "checkpoint_every_s" not in line))
    overrides = [f"resume={older}"]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        values = OmegaConf.to_container(compose("config", overrides=overrides), resolve=True)
    planned = plan(values, overrides)
    planned.lock.release()
    assert (planned.run.checkpoint_every, planned.run.checkpoint_every_s) == (3, None)
    out = tmp_path / "eval.csv"  # evaluate reads the run's configuration as it was saved
    evaluated = run_here("evaluate", [f"run={older}", f"out={out}"], tmp_path)
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]


def test_checkpoints_follow_the_clock_where_no_generations_are_given(tmp_path):
    """checkpoint_every=null: a checkpoint after every generation that ends checkpoint_every_s
    after the last one (here: every generation)."""
    run_dir = tmp_path / "clock"
    result = run_here("train", tiny(f"run_dir={run_dir}", "checkpoint_every=null",
                                    "checkpoint_every_s=1e-9", "keep_checkpoints=100"),
                      tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    _, metrics = read_csv(run_dir / rundir.METRICS)
    assert checkpoint_steps(run_dir) == list(range(1, len(metrics) + 1))


def test_resume_by_directory_refuses_other_explicit_settings(reference, tmp_path):
    run_dir, _ = reference
    before = _snapshot(run_dir)
    result = run_here("train", [f"resume={run_dir}", "env=hopper"], tmp_path)
    assert result.returncode == 2
    assert "env.name: checkpoint 'point', now 'hopper'" in result.stderr
    assert _snapshot(run_dir) == before


@pytest.mark.parametrize("extra, named", [
    (lambda other: [f"run_dir={other}"], "run_dir="),
    (lambda other: [f"output_dir={other}"], "output_dir="),
])
def test_resume_by_directory_refuses_another_directory_beside_it(reference, tmp_path, extra,
                                                                  named):
    run_dir, _ = reference
    before = _snapshot(run_dir)
    result = run_here("train", [f"resume={run_dir}", *extra(tmp_path / "other")], tmp_path)
    assert result.returncode == 2
    assert named in result.stderr and "would be ignored" in result.stderr
    assert _snapshot(run_dir) == before and not (tmp_path / "other").exists()


def test_resume_refuses_a_budget_below_the_steps_taken(reference, tmp_path):
    """A run cannot be shortened: resuming with total_steps under the checkpoint's env steps
    is refused and leaves its recorded settings as they were."""
    run_dir, _ = reference
    before = _snapshot(run_dir)
    result = run_here("train", [f"resume={run_dir}", f"total_steps={TOTAL // 2}"], tmp_path)
    assert result.returncode == 2
    assert f"total_steps={TOTAL // 2} is below the" in result.stderr
    assert "cannot be shortened" in result.stderr
    assert _snapshot(run_dir) == before


def test_resume_by_directory_takes_settings_equal_to_the_checkpoint_s(reference):
    """Each of these values, alone, breaks a rule against the command line's defaults
    (top_k=5 > pop_size, t_init=400 > t_max, warmup_steps=10,000 > buffer_size); against the
    checkpoint's settings, which they repeat, they hold."""
    from pgps_jax.cli.plan import plan
    run_dir, _ = reference
    overrides = [f"resume={run_dir}", "pgps.pop_size=4", "pgps.t_max=50",
                 "pgps.buffer_size=5000"]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        values = OmegaConf.to_container(compose("config", overrides=overrides), resolve=True)
    planned = plan(values, overrides)
    planned.lock.release()
    assert planned.resume_step == max(checkpoint_steps(run_dir))
    saved = OmegaConf.to_container(OmegaConf.load(run_dir / rundir.CONFIG), resolve=True)
    _, config = from_dict(saved)
    assert planned.config == config


def test_a_nan_loss_stops_the_run_and_keeps_the_last_good_checkpoint(
        monkeypatch, tmp_path, capsys):
    """The learning phase is wrapped to report a NaN critic loss at generation 3 (compiled
    afresh: not the programs that an earlier run of these settings left in this process)."""
    learn = PGPS.learn

    def poisoned(agent, state, played):
        state, metrics = learn(agent, state, played)
        loss = jnp.where(metrics["gen/generation"] == 3, jnp.nan, metrics["td3/critic_loss"])
        return state, {**metrics, "td3/critic_loss": loss}

    monkeypatch.setattr(PGPS, "learn", poisoned)
    monkeypatch.setattr(loop, "_JITTED", weakref.WeakKeyDictionary())
    run_dir = tmp_path / "nan"
    overrides = tiny("checkpoint_every=1", f"run_dir={run_dir}")
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        values = OmegaConf.to_container(compose("config", overrides=overrides), resolve=True)
    assert train.run(values, overrides) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "generation 3" in err and "td3/critic_loss" in err
    assert "last good checkpoint is generation 2" in err
    assert checkpoint_steps(run_dir) == [1, 2] and leftovers(run_dir) == []
    assert rundir.load_actors(run_dir / rundir.ACTORS)["generation"] == 2
    _, metrics = read_csv(run_dir / rundir.METRICS)
    assert metrics[-1]["generation"] == "3" and metrics[-1]["critic_loss"] == "nan"


def test_a_device_out_of_memory_is_one_line_naming_the_sizes(capsys):
    """XLA's allocation failure is reported as a failed run, with the settings that size the
    programs' memory, not as a traceback."""
    from pgps_jax.cli.errors import report
    assert report(lambda: jnp.zeros((2**40, 2**20)).block_until_ready()) == EXIT_FAILED
    err = capsys.readouterr().err
    assert err.startswith("error: the device ran out of memory (RESOURCE_EXHAUSTED")
    assert "pgps.buffer_size" in err and "pgps.ss1_size" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1

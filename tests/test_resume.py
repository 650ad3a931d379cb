"""Interrupted runs continue exactly, on hopper (real MJX physics, episodes that terminate
early): Ctrl-C mid-run, resume by directory, and the finished run's logs equal an
uninterrupted run's (same seed, same machine). SIGKILL at random moments: test_faults."""

import shutil
import signal

from pgps_jax.cli import run_dir as rundir

from conftest import HOPPER_RUN, reduced
from train_cli import (checkpoint_steps, data_rows, deterministic, leftovers, read_csv,
                       run_here, start, wait_until)

pytestmark = HOPPER_RUN


def assert_same_run(run_dir, reference):
    """eval.csv, eval_policies.csv and metrics.csv's deterministic columns equal the
    reference's; three checkpoints are kept and no temporary file is left."""
    assert (run_dir / rundir.EVAL).read_bytes() == (reference / rundir.EVAL).read_bytes()
    assert ((run_dir / rundir.EVAL_POLICIES).read_bytes()
            == (reference / rundir.EVAL_POLICIES).read_bytes())
    header, rows = read_csv(run_dir / rundir.METRICS)
    ref_header, ref_rows = read_csv(reference / rundir.METRICS)
    assert header == ref_header
    assert deterministic(rows) == deterministic(ref_rows)  # no row lost or repeated
    assert len(checkpoint_steps(run_dir)) == 3 and leftovers(run_dir) == []


def test_ctrl_c_writes_a_checkpoint_then_resume_by_directory(task_runs, cache, tmp_path):
    reference, _ = task_runs("hopper")
    run_dir = tmp_path / "interrupted"
    process = start("train", reduced("hopper", f"run_dir={run_dir}"), cache, tmp_path,
                    tmp_path / "log")
    wait_until(lambda: data_rows(run_dir / rundir.METRICS) >= 3, process)
    process.send_signal(signal.SIGINT)
    process.wait(timeout=300)
    log = (tmp_path / "log").read_text()
    assert process.returncode == 130, log[-3000:]
    assert "SIGINT: stopped at generation" in log and "checkpoint written" in log
    _, rows = read_csv(run_dir / rundir.METRICS)
    _, ref_rows = read_csv(reference / rundir.METRICS)
    assert len(rows) < len(ref_rows)
    stopped_at = int(rows[-1]["generation"])
    assert max(checkpoint_steps(run_dir)) == stopped_at  # the state at the stop, not older
    assert rundir.load_actors(run_dir / rundir.ACTORS)["generation"] == stopped_at
    assert leftovers(run_dir) == []
    # resume=<dir>: the run's own settings are used, none repeated on the command line
    result = run_here("train", [f"resume={run_dir}", "progress=false"], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"at generation {stopped_at}" in result.stdout
    assert_same_run(run_dir, reference)


def test_sigterm_before_the_loop_aborts_as_ctrl_c_does(cache, tmp_path):
    """SIGTERM as soon as the run directory is locked (the programs not yet compiled, no
    checkpoint written): the command says so and ends with status 130, not killed on the spot."""
    run_dir = tmp_path / "terminated"
    process = start("train", reduced("hopper", f"run_dir={run_dir}"), cache, tmp_path,
                    tmp_path / "log")
    wait_until((run_dir / rundir.LOCK).exists, process, poll=0.005)
    process.send_signal(signal.SIGTERM)
    process.wait(timeout=300)
    log = (tmp_path / "log").read_text()
    assert process.returncode == 130, log[-3000:]
    assert "aborted (Ctrl-C or SIGTERM) outside the generations' loop" in log
    assert "Traceback" not in log


def test_resuming_a_finished_run_changes_nothing(task_runs, tmp_path):
    reference, _ = task_runs("hopper")
    before = {p: p.read_bytes() for p in (reference / rundir.EVAL, reference / rundir.METRICS,
                                          reference / rundir.ACTORS)}
    result = run_here("train", reduced("hopper", f"run_dir={reference}", "resume=true"),
                      tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "done:" in result.stdout
    assert {p: p.read_bytes() for p in before} == before


def test_resume_by_directory_extends_the_budget_under_the_run_s_own_warm_up(task_runs,
                                                                            tmp_path):
    """total_steps=800 is below the command line's default warm-up (10,000) but above the
    run's (200): the run's settings decide."""
    reference, _ = task_runs("hopper")
    run_dir = tmp_path / "extended"
    shutil.copytree(reference, run_dir)
    before = data_rows(run_dir / rundir.METRICS)
    result = run_here("train", [f"resume={run_dir}", "total_steps=800", "progress=false"],
                      tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    _, rows = read_csv(run_dir / rundir.METRICS)
    assert len(rows) > before and int(rows[-1]["env_steps"]) >= 800
    assert int(rows[before - 1]["env_steps"]) < 800

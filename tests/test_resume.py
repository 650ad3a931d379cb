"""Interrupted runs continue exactly: SIGKILL or Ctrl-C mid-run, resume, and the finished
run's eval.csv equals an uninterrupted run's (same seed, same machine)."""

import signal

import pytest

from pgps_jax import run_dir as rundir

from train_cli import (checkpoint_steps, data_rows, deterministic, leftovers, read_csv, run,
                       start, tiny, wait_until)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("jax_cache")


@pytest.fixture(scope="module")
def reference(tmp_path_factory, cache):
    work = tmp_path_factory.mktemp("work")
    run_dir = work / "ref"
    result = run("train", tiny(f"run_dir={run_dir}"), cache, work)
    assert result.returncode == 0, result.stderr[-3000:]
    return run_dir


def _assert_same_run(run_dir, reference):
    assert (run_dir / rundir.EVAL).read_bytes() == (reference / rundir.EVAL).read_bytes()
    assert ((run_dir / rundir.EVAL_POLICIES).read_bytes()
            == (reference / rundir.EVAL_POLICIES).read_bytes())
    header, rows = read_csv(run_dir / rundir.METRICS)
    ref_header, ref_rows = read_csv(reference / rundir.METRICS)
    assert header == ref_header
    assert deterministic(rows) == deterministic(ref_rows)  # no row lost or repeated
    assert len(checkpoint_steps(run_dir)) == 3 and leftovers(run_dir) == []


def _interrupted(run_dir, reference) -> bool:
    _, rows = read_csv(run_dir / rundir.METRICS)
    _, ref_rows = read_csv(reference / rundir.METRICS)
    return len(rows) < len(ref_rows)


def test_sigkill_then_resume_equals_an_uninterrupted_run(reference, cache, tmp_path):
    run_dir = tmp_path / "killed"
    process = start("train", tiny(f"run_dir={run_dir}"), cache, tmp_path, tmp_path / "log")
    # kill once a checkpoint exists and the run has moved on past it
    wait_until(lambda: checkpoint_steps(run_dir) and data_rows(run_dir / rundir.METRICS)
               >= max(checkpoint_steps(run_dir)) + 2, process)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert process.returncode == -signal.SIGKILL
    assert _interrupted(run_dir, reference)
    killed_at = max(checkpoint_steps(run_dir))
    result = run("train", tiny(f"run_dir={run_dir}", "resume=true"), cache, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"resumed {run_dir} at generation {killed_at}" in result.stdout
    _assert_same_run(run_dir, reference)


def test_ctrl_c_writes_a_checkpoint_then_resume_by_directory(reference, cache, tmp_path):
    run_dir = tmp_path / "interrupted"
    process = start("train", tiny(f"run_dir={run_dir}"), cache, tmp_path, tmp_path / "log")
    wait_until(lambda: data_rows(run_dir / rundir.METRICS) >= 5, process)
    process.send_signal(signal.SIGINT)
    process.wait(timeout=300)
    log = (tmp_path / "log").read_text()
    assert process.returncode == 130, log[-3000:]
    assert "SIGINT: stopped at generation" in log and "checkpoint written" in log
    assert _interrupted(run_dir, reference)
    _, rows = read_csv(run_dir / rundir.METRICS)
    stopped_at = int(rows[-1]["generation"])
    assert max(checkpoint_steps(run_dir)) == stopped_at  # the state at the stop, not older
    assert rundir.load_actors(run_dir / rundir.ACTOR)["generation"] == stopped_at
    assert leftovers(run_dir) == []
    # resume=<dir>: the run's own settings are used, none repeated on the command line
    result = run("train", [f"resume={run_dir}", "progress=false"], cache, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"at generation {stopped_at}" in result.stdout
    _assert_same_run(run_dir, reference)


def test_resuming_a_finished_run_changes_nothing(reference, cache, tmp_path):
    before = {p: p.read_bytes() for p in (reference / rundir.EVAL, reference / rundir.METRICS)}
    result = run("train", tiny(f"run_dir={reference}", "resume=true"), cache, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "done:" in result.stdout
    assert {p: p.read_bytes() for p in before} == before

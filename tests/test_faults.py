"""Faults a long run survives, on hopper (real MJX physics): SIGKILL at random moments, a
damaged checkpoint, a full disk, a second process in the same run directory. After each,
the finished run's logs equal those of an uninterrupted run."""

import random
import shutil
import signal

import pytest

from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.checkpoint import DAMAGED

from conftest import HOPPER_RUN, reduced
import full_disk
from test_resume import assert_same_run
from train_cli import checkpoint_steps, data_rows, leftovers, run_here, start, wait_until

pytestmark = HOPPER_RUN

MOMENTS = ("checkpoint", "log")


def _checkpoint_in_progress(run_dir) -> bool:
    directory = run_dir / "checkpoints"
    return directory.exists() and any("orbax-checkpoint-tmp" in p.name
                                      for p in directory.iterdir())


def test_sigkill_at_random_moments_then_resume_equals_an_uninterrupted_run(task_runs, cache,
                                                                           tmp_path):
    """Killed while writing a checkpoint and right as a log line is written (mid-generation,
    its checkpoint not yet written), a seeded random number of generations in, resumed with
    resume=true after each."""
    reference, _ = task_runs("hopper")
    last_row = data_rows(reference / rundir.METRICS)
    chance = random.Random(0)
    run_dir = tmp_path / "chaos"
    args = reduced("hopper", f"run_dir={run_dir}", "resume=true", "checkpoint_every=1")
    moments = {
        "checkpoint": lambda rows: lambda: (data_rows(run_dir / rundir.METRICS) >= rows
                                            and _checkpoint_in_progress(run_dir)),
        "log": lambda rows: lambda: data_rows(run_dir / rundir.METRICS) >= rows,
    }
    killed = 0
    for kill, moment in enumerate(MOMENTS):
        rows = min(data_rows(run_dir / rundir.METRICS) + chance.randint(1, 3), last_row - 1)
        process = start("train", args, cache, tmp_path, tmp_path / f"log{kill}")
        wait_until(moments[moment](rows), process, poll=0.001)
        process.send_signal(signal.SIGKILL)
        process.wait()
        killed += process.returncode == -signal.SIGKILL
    assert killed == len(MOMENTS)
    result = run_here("train", args, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert_same_run(run_dir, reference)


def _flip_bytes(path) -> None:
    data = bytearray(path.read_bytes())
    for i in range(len(data) // 2, min(len(data), len(data) // 2 + 16)):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def _largest_state_file(checkpoint):
    return max((p for p in (checkpoint / "state").rglob("*") if p.is_file()),
               key=lambda p: p.stat().st_size)


def test_a_damaged_checkpoint_is_set_aside_and_the_run_resumes_from_the_one_before(
        task_runs, tmp_path):
    reference, _ = task_runs("hopper")
    run_dir = tmp_path / "damaged"
    shutil.copytree(reference, run_dir)
    steps = checkpoint_steps(run_dir)
    _flip_bytes(_largest_state_file(run_dir / "checkpoints" / str(steps[-1])))
    result = run_here("train", reduced("hopper", f"run_dir={run_dir}", "resume=true"),
                      tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"checkpoint {run_dir / 'checkpoints' / str(steps[-1])} is damaged" in result.stderr
    assert f"moved to {run_dir / DAMAGED / str(steps[-1])}" in result.stderr
    assert f"resumed {run_dir} at generation {steps[-2]}" in result.stdout
    assert (run_dir / DAMAGED / str(steps[-1]) / "state").is_dir()  # kept, not deleted
    assert "Traceback" not in result.stderr
    assert_same_run(run_dir, reference)


def test_when_no_checkpoint_verifies_resume_stops_with_a_message(task_runs, tmp_path):
    reference, _ = task_runs("hopper")
    run_dir = tmp_path / "all_damaged"
    shutil.copytree(reference, run_dir)
    steps = checkpoint_steps(run_dir)
    for step in steps:
        _flip_bytes(_largest_state_file(run_dir / "checkpoints" / str(step)))
    before = (run_dir / rundir.METRICS).read_bytes()
    result = run_here("train", reduced("hopper", f"run_dir={run_dir}", "resume=true"),
                      tmp_path)
    assert result.returncode == 2, result.stderr[-3000:]
    assert "no checkpoint in" in result.stderr and "can be restored" in result.stderr
    assert "Traceback" not in result.stderr
    assert sorted(int(p.name) for p in (run_dir / DAMAGED).iterdir()) == steps
    assert (run_dir / rundir.METRICS).read_bytes() == before


@pytest.mark.parametrize("where, n, file", [("checkpoint", 2, "checkpoints/4"),
                                            ("log", 3, rundir.METRICS)])
def test_a_full_disk_stops_the_run_with_a_message_and_resume_continues_it(
        task_runs, tmp_path, monkeypatch, where, n, file):
    reference, _ = task_runs("hopper")
    run_dir = tmp_path / "full"
    args = reduced("hopper", f"run_dir={run_dir}")
    with monkeypatch.context() as patched:
        full_disk.fill(where, n, patched.setattr)
        failed = run_here("train", args, tmp_path)
    assert failed.returncode == 1, failed.stderr[-3000:]
    assert f"error: cannot write {run_dir / file}: No space left on device" in failed.stderr
    assert "Traceback" not in failed.stderr and failed.stderr.count("\n") <= 3
    assert "resume=true" in failed.stderr
    assert checkpoint_steps(run_dir) == [2] and leftovers(run_dir) == []
    resumed = run_here("train", [*args, "resume=true"], tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resumed {run_dir} at generation 2" in resumed.stdout
    assert_same_run(run_dir, reference)


def test_a_second_process_in_a_run_directory_is_refused(task_runs, cache, tmp_path):
    run_dir = tmp_path / "busy"
    process = start("train", reduced("hopper", f"run_dir={run_dir}"), cache, tmp_path,
                    tmp_path / "log")
    try:
        wait_until(lambda: data_rows(run_dir / rundir.METRICS) >= 1, process)
        for extra in (["resume=true"], [f"resume={run_dir}"]):
            second = run_here("train", reduced("hopper", f"run_dir={run_dir}", *extra),
                              tmp_path)
            assert second.returncode == 2, second.stderr[-3000:]
            assert f"{run_dir} is in use by process {process.pid}" in second.stderr
            assert "Traceback" not in second.stderr
    finally:
        process.kill()
        process.wait()

"""The training command on each of the paper's five MuJoCo tasks (real MJX physics, a reduced
PGPS; the ant's frames on Euler's integrator, `conftest.REDUCED_PHYSICS`): it trains,
checkpoints, saves the actors, and `evaluate` reproduces its last evaluation on the physics
the run recorded."""

import numpy as np
import pytest

from pgps_jax.cli import run_dir as rundir
from pgps_jax.envs import TASKS

from conftest import HOPPER_RUN
from train_cli import checkpoint_steps, leftovers, read_csv, run_here


@pytest.mark.parametrize("task", [pytest.param(t, marks=HOPPER_RUN) if t == "hopper" else t
                                  for t in TASKS])
def test_train_checkpoints_and_evaluate_reproduces_the_last_evaluation(task, task_runs,
                                                                        tmp_path):
    run_dir, result = task_runs(task)
    assert "done:" in result.stdout and "final μ return" in result.stdout
    assert "warp" not in result.stdout + result.stderr  # mujoco.mjx's import lines are silenced
    _, rows = read_csv(run_dir / rundir.METRICS)
    generations = [int(r["generation"]) for r in rows]
    assert generations == list(range(1, len(rows) + 1)) and len(rows) >= 3
    assert all(np.isfinite(float(r["critic_loss"])) for r in rows)
    steps = checkpoint_steps(run_dir)
    assert len(steps) == 3 and steps[-1] == generations[-1] and leftovers(run_dir) == []
    actors = rundir.load_actors(run_dir / rundir.ACTORS)
    assert actors["generation"] == generations[-1]
    assert actors["mu"].shape == actors["td3"].shape == actors["elite"].shape

    out = tmp_path / "eval.csv"
    evaluated = run_here("evaluate", [f"run={run_dir}", f"out={out}"], tmp_path)
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    header, trained = read_csv(run_dir / rundir.EVAL)
    assert read_csv(out) == (header, [{**trained[-1], "": "0"}])

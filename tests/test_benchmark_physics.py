"""The benchmarks take a task's physics as `--env` and record the physics they measured on."""

import sys

import pytest

from benchmarks import grid_throughput
from benchmarks.timing import physics_record
from pgps_jax.envs import make_env


def test_the_record_names_the_physics_as_the_step_runs_it():
    record = physics_record(make_env("swimmer", start_pose="init_qpos", fused_solve=False,
                                     matmul_precision="default"))
    assert record["start_pose"] == "init_qpos" and record["matmul_precision"] == "default"
    assert record["fused_solve"] is False
    assert record["unroll_solver"] is False  # None resolved: off on the CPU


@pytest.mark.parametrize("argv, words", [
    (["seeds", "--env", "iterations=two"], ["--env iterations must be an integer"]),
    (["grid", "--env", "fused_solve=false"], ["--env applies to `seeds`"]),
])
def test_bad_physics_options_stop_the_grid_benchmark_before_it_measures(monkeypatch, capsys,
                                                                        argv, words):
    monkeypatch.setattr(sys, "argv", ["grid_throughput", *argv])
    with pytest.raises(SystemExit) as exit_:
        grid_throughput.main()
    assert exit_.value.code == 2
    for word in words:
        assert word in capsys.readouterr().err

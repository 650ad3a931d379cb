"""A training run records the physics it simulates and resumes only on it: `physics.*` on the
command line, the record in the run's configuration, and runs from before the record (whose
physics multiplied at JAX's default precision) read as such."""

import pytest

from pgps_jax.cli import plan as planning
from pgps_jax.cli.assignments import ENV_FIELDS
from pgps_jax.cli.errors import UsageError
from pgps_jax.cli.run_config import check_overrides, from_dict, physics_fields
from pgps_jax.cli.run_physics import BEFORE_RECORDED
from pgps_jax.envs import make_env

from test_run_config import composed


def test_the_command_line_offers_every_argument_of_make_env():
    assert physics_fields() == list(ENV_FIELDS)
    assert set(composed("env=hopper")["physics"]) == set(ENV_FIELDS)
    check_overrides(["env=hopper", "physics.fused_solve=false", "physics.iterations=2"])
    with pytest.raises(UsageError) as err:
        check_overrides(["physics.iteration=2"])
    assert "'physics.iteration'" in str(err.value) and "iterations" in str(err.value)


@pytest.mark.parametrize("override, words", [
    ("physics.integrator=leapfrog", ["integrator", "euler", "rk4"]),
    ("physics.iterations=two", ["physics iterations", "integer"]),
    ("physics.matmul_precision=tf32", ["matmul_precision", "highest", "default"]),
])
def test_bad_physics_is_refused_before_anything_is_written(tmp_path, override, words):
    run_dir = tmp_path / "run"
    with pytest.raises(UsageError) as err:
        planning.plan(composed("env=hopper", override, f"run_dir={run_dir}"))
    for word in words:
        assert word in str(err.value)
    assert not run_dir.exists()


def test_the_point_mass_takes_no_physics(tmp_path):
    with pytest.raises(UsageError) as err:
        planning.plan(composed("env=point", "physics.iterations=2", f"run_dir={tmp_path}/r"))
    assert "env=point has no MJX physics" in str(err.value)


def test_a_new_run_records_the_physics_it_simulates(tmp_path):
    p = planning.plan(composed("env=hopper", "physics.iterations=2", "physics.fused_solve=false",
                               f"run_dir={tmp_path}/run"))
    p.lock.release()
    expected = make_env("hopper", iterations=2).settings()
    assert {k: p.resolved["physics"][k] for k in expected} == expected
    assert p.resolved["physics"]["fused_solve"] is False  # how it computes: as given
    assert p.resolved["physics"]["unroll_solver"] is None  # the platform's default
    assert p.run.physics == p.resolved["physics"]


def _checkpointed(monkeypatch, saved_physics):
    """`plan` sees a checkpoint of a hopper run whose configuration holds `saved_physics`
    (absent: a run from before the record)."""
    saved = composed("env=hopper")
    saved.pop("physics")
    if saved_physics is not None:
        saved["physics"] = saved_physics
    monkeypatch.setattr(planning, "_checkpointed_config", lambda directory: (10, saved))
    monkeypatch.setattr(planning.rundir.RunDir, "has_checkpoint", lambda self: True)


def _resumed(tmp_path, *overrides):
    p = planning.plan(composed("env=hopper", f"run_dir={tmp_path}", *overrides), overrides)
    p.lock.release()
    return p


def test_a_run_from_before_the_record_resumes_on_its_precision_only(monkeypatch, tmp_path):
    _checkpointed(monkeypatch, None)
    with pytest.raises(UsageError) as err:
        _resumed(tmp_path, "resume=true")
    assert "physics.matmul_precision: checkpoint 'default', now 'highest'" in str(err.value)
    p = _resumed(tmp_path, "resume=true", "physics.matmul_precision=default")
    assert p.run.physics["matmul_precision"] == "default" == BEFORE_RECORDED["matmul_precision"]
    p = _resumed(tmp_path, f"resume={tmp_path}")
    assert p.run.physics["matmul_precision"] == "default"
    assert {k: p.run.physics[k] for k in ("integrator", "iterations")} == {
        "integrator": "euler", "iterations": make_env("hopper").physics.iterations}


def test_a_recorded_run_resumes_on_its_physics(monkeypatch, tmp_path):
    recorded = composed("env=hopper", "physics.iterations=2")["physics"]
    _checkpointed(monkeypatch, recorded)
    with pytest.raises(UsageError) as err:
        _resumed(tmp_path, "resume=true")
    assert "physics.iterations: checkpoint 2, now 1" in str(err.value)
    assert _resumed(tmp_path, f"resume={tmp_path}").run.physics["iterations"] == 2
    # how the physics is computed may change; what it simulates may not
    p = _resumed(tmp_path, f"resume={tmp_path}", "physics.fused_solve=false")
    assert p.run.physics["fused_solve"] is False and p.run.physics["iterations"] == 2
    with pytest.raises(UsageError) as err:
        _resumed(tmp_path, f"resume={tmp_path}", "physics.iterations=3")
    assert "physics.iterations: checkpoint 2, now 3" in str(err.value)


def test_tools_read_a_run_from_before_the_record_at_its_precision():
    run, _ = from_dict({k: v for k, v in composed("env=hopper").items() if k != "physics"})
    assert run.physics is None
    from pgps_jax.cli.run_physics import as_run, env_for
    assert env_for("hopper", as_run("hopper", run.physics)).physics.matmul_precision == "default"

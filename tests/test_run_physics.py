"""A training run records the physics it simulates and resumes only on it: `physics.*` on the
command line, the record in the run's configuration and what the trainer, `evaluate` and
`render` build from it; a run from before the record resumes only with its physics stated."""

import pytest

from pgps_jax.cli import evaluate, plan as planning, run_physics, trainer
from pgps_jax.cli.assignments import ENV_FIELDS, checked_env_kwargs
from pgps_jax.cli.errors import UsageError
from pgps_jax.cli.run_config import check_overrides, from_dict, physics_fields
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
    ("physics.iterations=two", ["physics.iterations must be an integer"]),
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
    assert "env=point has no MJX physics" in str(err.value) and "hopper" in str(err.value)


def test_a_setting_that_is_not_make_env_s_is_named():
    with pytest.raises(UsageError) as err:
        checked_env_kwargs({"iteration": 2}, "physics.")
    assert "physics.iteration: not a physics setting" in str(err.value)
    assert "iterations" in str(err.value)


class _Built(Exception):
    """Stops `trainer.train` once the agent's env is built."""


def test_a_new_run_records_the_physics_it_simulates_and_trains_on_it(monkeypatch, tmp_path):
    p = planning.plan(composed("env=hopper", "physics.iterations=2", "physics.fused_solve=false",
                               f"run_dir={tmp_path}/run"))
    expected = make_env("hopper", iterations=2).settings()
    assert {k: p.resolved["physics"][k] for k in expected} == expected
    assert p.resolved["physics"]["fused_solve"] is False  # how it computes: as given
    assert p.resolved["physics"]["unroll_solver"] is None  # the platform's default
    built = []

    def make_agent(algo, config, env, evaluation):
        built.append(env)
        raise _Built
    monkeypatch.setattr(trainer, "make_agent", make_agent)
    try:
        with pytest.raises(_Built):
            trainer.train(p)
    finally:
        p.lock.release()
    assert built[0].settings() == expected and built[0].physics.fused_solve is False
    assert built[0] is make_env("hopper", iterations=2, fused_solve=False)  # built once
    written = p.directory.read_config()["physics"]
    assert written["iterations"] == 2 and written["fused_solve"] is False


def test_the_point_mass_records_no_physics(tmp_path):
    p = planning.plan(composed("env=point", f"run_dir={tmp_path}/run"))
    p.lock.release()
    assert set(p.resolved["physics"]) == set(ENV_FIELDS)
    assert all(v is None for v in p.resolved["physics"].values())


def _checkpointed(monkeypatch, task, saved_physics):
    """`plan` sees a checkpoint of a run of `task` whose configuration holds `saved_physics`
    (None: a run from before the record)."""
    saved = composed(f"env={task}")
    saved.pop("physics")
    if saved_physics is not None:
        saved["physics"] = saved_physics
    monkeypatch.setattr(planning, "_checkpointed",
                        lambda directory: (10, {"config": saved, "total_steps": 0}))
    monkeypatch.setattr(planning.rundir.RunDir, "has_checkpoint", lambda self: True)


def _resumed(tmp_path, *overrides, task="hopper"):
    p = planning.plan(composed(f"env={task}", f"run_dir={tmp_path}", *overrides), overrides)
    p.lock.release()
    return p


def test_a_run_from_before_the_record_resumes_only_with_its_physics_stated(monkeypatch,
                                                                           tmp_path):
    _checkpointed(monkeypatch, "hopper", None)
    for how in ("resume=true", f"resume={tmp_path}"):
        with pytest.raises(UsageError) as err:
            _resumed(tmp_path, how)
        assert "does not record its physics" in str(err.value)
        assert "physics.matmul_precision=default" in str(err.value)
        p = _resumed(tmp_path, how, "physics.matmul_precision=default")
        assert p.run.physics["matmul_precision"] == "default"
        assert p.run.physics["iterations"] == make_env("hopper").physics.iterations


def test_a_point_mass_run_from_before_the_record_resumes(monkeypatch, tmp_path):
    _checkpointed(monkeypatch, "point", None)
    assert all(v is None for v in _resumed(tmp_path, "resume=true",
                                           task="point").run.physics.values())


def test_a_recorded_run_resumes_on_its_physics(monkeypatch, tmp_path):
    node = composed("env=hopper", "physics.iterations=2", "physics.fused_solve=false")["physics"]
    _checkpointed(monkeypatch, "hopper", run_physics.recorded("hopper", node))
    with pytest.raises(UsageError) as err:
        _resumed(tmp_path, "resume=true")
    assert "physics.iterations: checkpoint 2, now 1" in str(err.value)
    assert "fused_solve" not in str(err.value)  # how it is computed may change
    assert _resumed(tmp_path, "resume=true", "physics.iterations=2").run.physics[
        "fused_solve"] is None
    p = _resumed(tmp_path, f"resume={tmp_path}")
    assert p.run.physics["iterations"] == 2 and p.run.physics["fused_solve"] is False
    p = _resumed(tmp_path, f"resume={tmp_path}", "physics.fused_solve=true")
    assert p.run.physics["fused_solve"] is True and p.run.physics["iterations"] == 2
    with pytest.raises(UsageError) as err:
        _resumed(tmp_path, f"resume={tmp_path}", "physics.iterations=3")
    assert "physics.iterations: checkpoint 2, now 3" in str(err.value)


def test_another_task_is_the_one_difference_named(monkeypatch, tmp_path):
    _checkpointed(monkeypatch, "hopper", run_physics.recorded("hopper", {}))
    for how in ("resume=true", f"resume={tmp_path}"):
        with pytest.raises(UsageError) as err:
            _resumed(tmp_path, how, "env=point", task="point")
        assert "env.name: checkpoint 'hopper', now 'point'" in str(err.value)
        assert "physics" not in str(err.value)


def test_evaluate_builds_the_run_s_physics_and_warns_where_it_is_not_recorded(monkeypatch,
                                                                             capsys):
    recorded = composed("env=hopper", "physics.iterations=2")
    settings, config = from_dict(recorded)
    built = []

    def evaluate_actors(algo, config, evaluation, env, saved, key):
        built.append(env)
        raise _Built
    monkeypatch.setattr(evaluate, "evaluate_actors", evaluate_actors)
    monkeypatch.setattr(evaluate, "load_run", lambda path: (settings, config, {}))
    with pytest.raises(_Built):
        evaluate._evaluate(["run=runs/hopper/seed0"])
    assert built[-1].physics.iterations == 2
    assert "warning" not in capsys.readouterr().err
    settings, config = from_dict({k: v for k, v in recorded.items() if k != "physics"})
    assert settings.physics is None
    with pytest.raises(_Built):
        evaluate._evaluate(["run=runs/hopper/seed0"])
    assert built[-1].settings() == make_env("hopper").settings()
    assert "runs/hopper/seed0 does not record its physics" in capsys.readouterr().err

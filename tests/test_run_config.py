"""run_config: Hydra YAML -> (RunSettings, PGPSConfig), override checks, config differences."""


import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pgps_jax.agent.config import EvaluationConfig, PGPSConfig, for_task
from pgps_jax.cli.errors import UsageError
from pgps_jax.cli.run_config import (CONFIG_DIR, IDENTITY_KEYS, PGPS_FIELDS,
                                 check_overrides, coerce, differences, env_choices,
                                 explicitly_set, from_dict, override_keys, pgps_config,
                                 register_structured_configs)
from pgps_jax.cli.trainer import first_non_finite

MUJOCO_TASKS = ("halfcheetah", "hopper", "walker2d", "ant", "swimmer")
register_structured_configs()


def composed(*overrides: str) -> dict:
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


def test_defaults_are_the_issue_defaults():
    run, config = from_dict(composed())
    assert (run.env, run.seed, run.total_steps, run.eval_every) == ("halfcheetah", 0, 1_000_000, 10_000)
    assert (run.keep_checkpoints, run.resume, run.run_dir) == (3, False, "runs/halfcheetah/seed0")
    assert (run.checkpoint_every, run.checkpoint_every_s) == (None, 120.0)  # by the clock
    assert config == for_task("halfcheetah")


@pytest.mark.parametrize("task", MUJOCO_TASKS)
def test_env_yaml_gives_table_4(task):
    run, config = from_dict(composed(f"env={task}"))
    assert run.env == task
    assert config == for_task(task)


def test_every_pgps_field_is_in_the_composed_config():
    assert set(composed()["pgps"]) == set(PGPS_FIELDS)
    assert set(env_choices()) == set(MUJOCO_TASKS) | {"point"}


def test_issue_overrides():
    run, config = from_dict(composed("env=hopper", "seed=3", "total_steps=200000",
                                     "pgps.q_filter=false", "pgps.pop_size=4"))
    assert (run.env, run.seed, run.total_steps, run.run_dir) == ("hopper", 3, 200_000, "runs/hopper/seed3")
    assert config == for_task("hopper", q_filter=False, pop_size=4)


def test_point_preset_is_tiny_and_valid():
    run, config = from_dict(composed("env=point"))
    assert config.actor_hidden == config.critic_hidden == (32, 32)
    assert config.pop_size * config.t_max <= config.buffer_size <= 10_000
    assert run.total_steps <= 10_000


@pytest.mark.parametrize("args, words", [
    (["pgps.foo=1"], ["'pgps.foo'", "pop_size", "q_filter"]),
    (["foo=1"], ["'foo'", "seed", "total_steps", "pgps.<field>"]),
    (["env=humanoid"], ["'humanoid'", "halfcheetah", "hopper", "walker2d", "ant", "swimmer"]),
    (["env.name=hopper"], ["env=<task>"]),
    (["env=[hopper,ant]"], ["env= takes one task", "halfcheetah", "swimmer"]),
    (["algo=[td3,cem]"], ["algo= takes one algorithm", "cemrl", "pgps"]),
    (["pgps=5"], ["pgps=5 is not a setting", "pgps.<field>=value", "pop_size"]),
    (["pgps={pop_size:4,bogus:1}"], ["pgps.<field>=value", "top_k"]),
    (["-m", "env=hopper,ant"], ["env=hopper,ant: env= takes one task", "walker2d"]),
    (["algo=td3", "pgps={q_filter:true}"], ["pgps.q_filter", "algo=td3 has none"]),
    (["-m", "foo"], ["'foo' is not a setting"]),
    (["env=hopper", "foo"], ["'foo' is not a setting", "key=value", "total_steps"]),
    (["algo=td3", "pgps.q_filter=true"], ["pgps.q_filter", "algo=td3 has none", "algo=pgps"]),
    (["algo=cemrl", "pgps.ea_guides_pg=true"], ["pgps.ea_guides_pg", "increasing_steps"]),
])
def test_check_overrides_names_the_key_and_the_choices(args, words):
    with pytest.raises(UsageError) as err:
        check_overrides(args)
    for word in words:
        assert word in str(err.value)


def test_check_overrides_accepts_valid_and_hydra_flags():
    check_overrides(["env=hopper", "seed=3", "pgps.q_filter=false", "resume=true",
                     "hydra.verbose=true", "--cfg", "job", "pgps={pop_size:4}"])
    check_overrides(["algo=pgps", "pgps.q_filter=false", "pgps.increasing_steps=false"])
    check_overrides(["pgps=table3", "~pgps.q_filter", "--config-name", "config"])


@pytest.mark.parametrize("values, words", [
    ({"pop_size": "ten"}, ["pgps.pop_size", "integer"]),
    ({"q_filter": 1}, ["pgps.q_filter", "true or false"]),
    ({"actor_hidden": 64}, ["pgps.actor_hidden"]),
    ({"top_k": 99}, ["top_k", "99"]),
    ({"bogus": 1}, ["pgps.bogus", "pop_size"]),
])
def test_bad_pgps_values_name_the_field(values, words):
    with pytest.raises(UsageError) as err:
        pgps_config(values)
    for word in words:
        assert word in str(err.value)


def test_pgps_config_coerces_yaml_types():
    config = pgps_config({"buffer_size": 50000.0, "actor_hidden": [32, 32], "tau": 1})
    assert config.buffer_size == 50000 and isinstance(config.buffer_size, int)
    assert config.actor_hidden == (32, 32) and config.tau == 1.0


def test_coerce_gives_python_values_and_names_what_a_value_must_be():
    """A numpy integer becomes an int (a configuration is written as JSON); a value of another
    type is refused in the words of `field_types.mismatch`."""
    assert type(coerce("pgps.batch_size", np.int64(32), int)) is int
    assert coerce("pgps.actor_hidden", [np.int64(8)], tuple[int, ...]) == (8,)
    assert type(coerce("pgps.actor_hidden", [np.int64(8)], tuple[int, ...])[0]) is int
    for value, kind, words in ((5, str, "must be a string, got 5"),
                               ("", str, "must be a non-empty string, got ''"),
                               (True, int, "must be an integer, got True"),
                               (1, bool, "must be true or false, got 1")):
        with pytest.raises(UsageError, match=words):
            coerce("key", value, kind)


@pytest.mark.parametrize("key, value, words", [
    ("total_steps", 0, ["total_steps=0", ">= 1"]),
    ("eval_every", "often", ["eval_every", "integer"]),
    ("resume", 3, ["resume"]),
    ("checkpoint_every", 0, ["checkpoint_every=0", ">= 1, or null"]),
    ("checkpoint_every_s", 0, ["checkpoint_every_s=0", "positive number of seconds"]),
    ("checkpoint_every_s", float("inf"), ["checkpoint_every_s=inf", "or null"]),
    ({"checkpoint_every": None, "checkpoint_every_s": None}, None,
     ["both null", "only at its end"]),
])
def test_bad_run_settings_name_the_key(key, value, words):
    values = composed("env=point")
    values.update(key if isinstance(key, dict) else {key: value})
    with pytest.raises(UsageError) as err:
        from_dict(values)
    for word in words:
        assert word in str(err.value)


def test_differences_name_the_fields():
    saved = composed("env=point")
    now = composed("env=point", "pgps.q_filter=false", "seed=4", "total_steps=9999")
    lines = differences(saved, now, IDENTITY_KEYS)
    assert len(lines) == 2
    assert any(l.startswith("pgps.q_filter: checkpoint True, now False") for l in lines)
    assert any(l.startswith("seed: checkpoint 0, now 4") for l in lines)
    assert differences(saved, composed("env=point"), IDENTITY_KEYS) == []
    # 5 and 5.0 are the same value; True and 1 are not
    assert differences({"a": 5}, {"a": 5.0}, ["a"]) == []
    assert differences({"a": True}, {"a": 1}, ["a"]) != []


def test_explicitly_set_covers_groups():
    keys = override_keys(["env=hopper", "pgps.pop_size=4", "seed=1"])
    assert keys == ["env", "pgps.pop_size", "seed"]
    assert explicitly_set("env.name", keys) and explicitly_set("pgps.pop_size", keys)
    assert not explicitly_set("pgps.top_k", keys)


def test_first_non_finite_names_the_loss_first():
    metrics = {"a/x": 1.0, "td3/actor_loss": float("nan"), "td3/critic_loss": float("inf"),
               "td3/return": float("nan"), "td3/in_population": False}
    assert first_non_finite(metrics) == "td3/critic_loss"
    assert first_non_finite({"td3/return": float("nan"), "td3/in_population": False}) is None
    assert first_non_finite({"td3/return": float("nan"), "td3/in_population": True}) == "td3/return"
    assert first_non_finite({"gen/generation": 3, "x": 1.5}) is None
    # eval/* is NaN by design when no evaluation was due
    assert first_non_finite({"eval/done": False, "eval/mu_mean": float("nan")}) is None
    assert first_non_finite({"eval/done": True, "eval/mu_mean": float("nan")}) == "eval/mu_mean"


def test_the_evaluation_settings_are_the_run_s_not_the_algorithm_s():
    run, _ = from_dict(composed("env=point", "eval_every=123", "eval_episodes=4"))
    assert run.evaluation == EvaluationConfig(every=123, episodes=4, steps=50)  # point.yaml
    assert {"eval_every", "eval_episodes", "eval_steps"} <= set(IDENTITY_KEYS)
    with pytest.raises(UsageError, match=r"pgps.eval_steps is not a PGPSConfig field: set "
                                         r"eval_steps=\.\.\."):
        check_overrides(["pgps.eval_steps=5"])


@pytest.mark.parametrize("total_steps", [100, 200])
def test_a_budget_within_the_warm_up_is_refused_before_anything_is_written(tmp_path,
                                                                          total_steps):
    from pgps_jax.cli.plan import plan
    run_dir = tmp_path / "run"
    values = composed("env=point", f"total_steps={total_steps}", "pgps.warmup_steps=200",
                      f"run_dir={run_dir}")
    with pytest.raises(UsageError) as err:
        plan(values)
    assert (f"total_steps={total_steps} does not exceed the random warm-up "
            "(pgps.warmup_steps=200)") in str(err.value)
    assert not run_dir.exists()


def test_a_checkpoint_from_before_the_authors_details_resumes_as_it_ran():
    """Runs saved before `resample_before_q_filter` and `fell_behind_rule` existed sampled
    their population every generation and guided the TD3 actor below mean − std; resumed,
    they go on doing so, although the defaults are now the authors' code's; a field whose
    default is the behaviour from before it (`beta_adapted`, `target_actor_from_elite`,
    `update_unroll`) takes its default."""
    from pgps_jax.cli.plan import _with_new_fields
    completed = _with_new_fields({"algo": {"name": "pgps"}, "pgps": {"pop_size": 6}})["pgps"]
    before = dict(resample_before_q_filter=True, fell_behind_rule="mean_minus_std")
    for name, value in before.items():
        assert completed[name] == value
        assert getattr(PGPSConfig(), name) != value
    assert completed["pop_size"] == 6
    assert completed["update_unroll"] == PGPSConfig().update_unroll
    assert completed["beta_adapted"] == PGPSConfig().beta_adapted == "before_block"
    assert completed["target_actor_from_elite"] is PGPSConfig().target_actor_from_elite is False


def test_a_switch_without_effect_does_not_stop_a_checkpoint_from_resuming():
    """A TD3 checkpoint saved when `resample_before_q_filter` defaulted to true resumes under
    today's default: without Q-filtering the switch does nothing. PGPS's is compared."""
    import dataclasses
    from pgps_jax.cli.plan import _comparable
    from pgps_jax.cli.run_config import differences

    def settings(algo, **changes):
        return {"pgps": dataclasses.asdict(for_task("hopper", algo, **changes))}
    keys = [f"pgps.{f.name}" for f in dataclasses.fields(PGPSConfig)]
    old, now = settings("td3", resample_before_q_filter=True), settings("td3")
    assert differences(old, now, keys) == [
        "pgps.resample_before_q_filter: checkpoint True, now False"]
    assert differences(_comparable(old), _comparable(now), keys) == []
    assert differences(_comparable(settings("pgps", resample_before_q_filter=True)),
                       _comparable(settings("pgps")), keys) == [
        "pgps.resample_before_q_filter: checkpoint True, now False"]

"""PGPSConfig: Table 3/4 presets and eager validation with actionable messages."""

import dataclasses
import json

import numpy as np
import pytest

from pgps_jax.agent.config import (TASK_NAMES, EvaluationConfig, PGPSConfig, check_for_algorithm,
                                    for_task, recorded_episodes)


def test_defaults_are_table_3():
    c = PGPSConfig()
    assert (c.tau, c.actor_lr, c.critic_lr, c.gamma) == (0.005, 2e-3, 1e-3, 0.99)
    assert (c.buffer_size, c.batch_size, c.sigma_init, c.sigma_limit) == (1_000_000, 256, 7.5e-3, 1e-5)
    assert (c.beta_init, c.d_target, c.ss2_size, c.ss1_size) == (1.0, 0.05, 512, 64)
    assert (c.q_filter_start, c.sample_ratio) == (150_000, 50)
    assert (c.t_max, c.t_init, c.t_interval) == (1000, 400, 100_000)
    assert c.actor_hidden == c.critic_hidden == (400, 300)


def test_where_the_paper_and_the_authors_code_differ_the_defaults_are_each_in_two():
    """The authors' code for the population and the guiding rule; Algorithm 1's order of β's
    adaptation and Algorithm 3's target actor."""
    c = PGPSConfig()
    assert (c.resample_before_q_filter, c.beta_adapted, c.fell_behind_rule,
            c.target_actor_from_elite) == (False, "before_block", "mean", False)
    swimmer = for_task("swimmer")
    assert (swimmer.t_init, swimmer.d_target) == (500, 0.03)
    for task in ("halfcheetah", "hopper", "walker2d", "ant"):
        assert (for_task(task).t_init, for_task(task).d_target) == (400, 0.05)
    for algo in ("cem", "td3", "cemrl"):
        assert not for_task("hopper", algo).target_actor_from_elite


@pytest.mark.parametrize("task, n, k, f, tau_sigma", [
    ("swimmer", 10, 5, 3, 0.01), ("halfcheetah", 10, 5, 1, 0.03), ("hopper", 6, 3, 1, 0.03),
    ("walker2d", 6, 3, 1, 0.03), ("ant", 6, 3, 1, 0.03)])
def test_table_4_presets(task, n, k, f, tau_sigma):
    c = for_task(task)
    assert (c.pop_size, c.top_k, c.td3_to_cem_period, c.sigma_decay) == (n, k, f, tau_sigma)


def test_preset_overrides_apply():
    assert for_task("hopper", q_filter=False).q_filter is False


def test_unknown_task_lists_choices():
    with pytest.raises(ValueError) as err:
        for_task("humanoid")
    assert "humanoid" in str(err.value)
    for name in TASK_NAMES:
        assert name in str(err.value)
    with pytest.raises(ValueError, match=r"unknown task 'point'.*configs/env/point\.yaml"):
        for_task("point")


@pytest.mark.parametrize("changes, field, hint", [
    (dict(pop_size=1, top_k=1), "pop_size", ">= 2"),
    (dict(top_k=0), "top_k", "[1, pop_size=10]"),
    (dict(top_k=11), "top_k", "[1, pop_size=10]"),
    (dict(batch_size=0), "batch_size", "positive integer"),
    (dict(buffer_size=-5), "buffer_size", "positive integer"),
    (dict(t_init=0), "t_init", "positive integer"),
    (dict(t_max=-1), "t_max", "positive integer"),
    (dict(ss1_size=0), "ss1_size", "positive integer"),
    (dict(sample_ratio=0), "sample_ratio", "> 0"),
    (dict(tau=0.0), "tau", "(0, 1]"),
    (dict(gamma=1.0), "gamma", "[0, 1)"),
    (dict(actor_lr=-1e-3), "actor_lr", "> 0"),
    (dict(t_init=2000), "t_init", "<= t_max=1000"),
    (dict(fell_behind_rule="median"), "fell_behind_rule", "one of mean_minus_std, mean"),
    (dict(beta_adapted="later"), "beta_adapted", "one of before_block, after_block"),
    (dict(pop_size=6, top_k=3, buffer_size=1000, warmup_steps=1000), "warmup_steps",
     "1002 rows"),
    (dict(buffer_size=2**31), "buffer_size", "< 2**31"),
    (dict(buffer_size=20_000, warmup_steps=1000, batch_size=50_000), "batch_size",
     "<= buffer_size=20000"),
    (dict(buffer_size=20_000, warmup_steps=1000, ss1_size=100_000), "ss1_size",
     "<= buffer_size=20000"),
    (dict(buffer_size=20_000, warmup_steps=1000, ss2_size=20_001), "ss2_size",
     "<= buffer_size=20000"),
])
def test_invalid_values_name_field_value_and_range(changes, field, hint):
    with pytest.raises(ValueError) as err:
        PGPSConfig(**changes)
    message = str(err.value)
    assert f"PGPSConfig.{field}=" in message
    assert repr(changes[field]) in message
    assert hint in message


@pytest.mark.parametrize("algo, changes, episodes", [
    ("pgps", dict(), 10),
    ("pgps", dict(pg_guides_ea=False), 11),       # the TD3 actor's extra episode
    ("cemrl", dict(), 10),
    ("td3", dict(exploring_episodes=3), 3),
])
def test_the_buffer_holds_one_generation_of_the_algorithm_s_recorded_episodes(
        algo, changes, episodes):
    rows = episodes * 1000
    config = for_task("halfcheetah", algo, buffer_size=rows, warmup_steps=1000, **changes)
    assert recorded_episodes(algo, config) == episodes
    check_for_algorithm(algo, config)
    small = config.replace(buffer_size=rows - 1)
    with pytest.raises(ValueError) as err:
        check_for_algorithm(algo, small)
    assert f"PGPSConfig.buffer_size={rows - 1}" in str(err.value)
    assert f"{episodes} episodes × t_max = {rows}" in str(err.value)


@pytest.mark.parametrize("changes, field, valid", [
    (dict(q_filter="false"), "q_filter", "True or False"),
    (dict(elitism=0), "elitism", "True or False"),
    (dict(batch_size=True), "batch_size", "an integer"),
    (dict(pop_size=2.5), "pop_size", "an integer"),
    (dict(pop_size="4"), "pop_size", "an integer"),
    (dict(actor_lr="1e-3"), "actor_lr", "a finite number"),
    (dict(sigma_init=float("inf")), "sigma_init", "a finite number"),
    (dict(d_target=float("nan")), "d_target", "a finite number"),
    (dict(actor_hidden=(16.5,)), "actor_hidden", "a tuple of integer layer widths"),
    (dict(critic_hidden=16), "critic_hidden", "a tuple of integer layer widths"),
    (dict(fell_behind_rule=1), "fell_behind_rule", "a string"),
])
def test_a_value_of_the_wrong_type_is_named_before_any_range(changes, field, valid):
    with pytest.raises(ValueError, match=rf"^PGPSConfig\.{field}=.* must be {valid}$"):
        for_task("hopper", **changes)


def test_numpy_scalars_and_lists_are_stored_as_python_values():
    config = for_task("hopper", batch_size=np.int64(16), actor_hidden=[16, np.int32(8)],
                      q_filter=np.bool_(False), actor_lr=np.float32(0.5),
                      critic_lr=np.int64(1))
    assert (type(config.batch_size), type(config.q_filter), type(config.actor_lr),
            type(config.critic_lr)) == (int, bool, float, float)
    assert config.actor_hidden == (16, 8) and config.actor_lr == 0.5
    assert json.loads(json.dumps(dataclasses.asdict(config)))["batch_size"] == 16
    assert hash(config) == hash(for_task("hopper", batch_size=16, actor_hidden=(16, 8),
                                         q_filter=False, actor_lr=0.5, critic_lr=1.0))
    assert type(EvaluationConfig(every=np.int64(100)).every) is int
    with pytest.raises(ValueError, match=r"EvaluationConfig\.every=True .* an integer"):
        EvaluationConfig(every=True)


def test_too_few_candidates_for_half_population():
    # SR·N must supply at least the N/2 actors that Q-filtering selects.
    with pytest.raises(ValueError) as err:
        PGPSConfig(pop_size=10, top_k=5, sample_ratio=0.4)
    assert "PGPSConfig.sample_ratio=0.4" in str(err.value)
    assert "4 candidates >= the 5 population slots" in str(err.value)
    assert PGPSConfig(pop_size=10, top_k=5, sample_ratio=0.5).num_candidates == 5

"""The agent end to end on the toy env: schedule, tracing, vmap, determinism, learning and the
test evaluations that ride along."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pgps_jax.agent import pgps
from pgps_jax.agent.config import INERT_WITHOUT, EvaluationConfig, PGPSConfig, effective_fields
from pgps_jax.envs.point import PointMass
from pgps_jax.agent.networks import flatten
from pgps_jax.agent.pgps import PGPS

ENV = PointMass()
SMALL = PGPSConfig(pop_size=4, top_k=2, actor_hidden=(16, 16), critic_hidden=(16, 16),
                   buffer_size=2000, warmup_steps=100, batch_size=32, ss2_size=32, ss1_size=16,
                   sample_ratio=3, q_filter_start=200, t_init=10, t_max=20, t_interval=150,
                   t_increment=5)
TESTS = EvaluationConfig(episodes=3, steps=20)


def evaluated_every(every: int, **changes) -> EvaluationConfig:
    return dataclasses.replace(TESTS, every=every, **changes)


@functools.lru_cache(maxsize=None)
def programs(config, evaluation=TESTS, donate=True):
    """The agent of `config` on the toy env, its jitted init and generation_step (made once
    per configuration, so that the tests of one configuration share their programs)."""
    agent = PGPS(config, ENV, evaluation)
    return (agent, jax.jit(agent.init),
            jax.jit(agent.generation_step, donate_argnums=0 if donate else ()))


@pytest.mark.parametrize("steps, expected", [(0, 400), (99_999, 400), (100_000, 500),
                                             (250_000, 600), (600_000, 1000), (5_000_000, 1000)])
def test_episode_limit_eq_4(steps, expected):
    assert int(pgps.episode_limit(jnp.asarray(steps), PGPSConfig())) == expected


def test_episode_limit_fixed_without_increasing_steps():
    config = PGPSConfig(increasing_steps=False)
    assert int(pgps.episode_limit(jnp.asarray(0), config)) == 1000


def test_fell_behind_is_below_mean_minus_std():
    returns = jnp.array([10.0, 20.0, 30.0, 40.0])        # mean 25, std ≈ 11.18
    assert bool(pgps.fell_behind(jnp.asarray(13.0), returns, "mean_minus_std"))
    assert not bool(pgps.fell_behind(jnp.asarray(14.0), returns, "mean_minus_std"))


@pytest.mark.parametrize("rule", ["mean_minus_std", "mean"])
def test_fell_behind_rules_match_numpy(rule):
    returns = np.random.default_rng(0).normal(100.0, 30.0, size=(50, 6)).astype(np.float32)
    for row in returns:
        threshold = row.mean() - (row.std() if rule == "mean_minus_std" else 0.0)
        for td3_return in (threshold - 1.0, threshold + 1.0, row.mean() - 0.5 * row.std()):
            assert (bool(pgps.fell_behind(jnp.asarray(td3_return), jnp.asarray(row), rule))
                    == bool(td3_return < threshold))


@pytest.mark.parametrize("from_elite,ea_guides_pg", [(True, True), (False, True),
                                                     (True, False)])
def test_the_target_actor_starts_each_generation_at_the_elite_only_when_asked(from_elite,
                                                                              ea_guides_pg):
    """With τ tiny, the target actor after a generation's updates is where they began: the new
    elite with `target_actor_from_elite`, with EA→PG or without it (as the authors' code
    does), else the old target."""
    config = SMALL.replace(tau=1e-7, target_actor_from_elite=from_elite,
                           ea_guides_pg=ea_guides_pg)
    _, init, step = programs(config, donate=False)
    state = init(jax.random.PRNGKey(1))  # a sample beats the elite
    target_before = np.asarray(flatten(state.td3.actor_target))
    new, _ = step(state)
    target_after = np.asarray(flatten(new.td3.actor_target))
    start = np.asarray(new.cem.elite) if from_elite else target_before
    assert not np.allclose(np.asarray(new.cem.elite), target_before, atol=1e-3)
    np.testing.assert_allclose(target_after, start, atol=1e-4)


# Other valid values of the settings `INERT_WITHOUT` names (SMALL's t_max is 20).
_CHANGED = dict(resample_before_q_filter=True, fell_behind_rule="mean_minus_std", beta_min=1e-2,
                beta_max=8.0, d_target=0.2, ss2_size=8, beta_adapted="after_block", t_init=15,
                t_interval=40, t_increment=2)


@pytest.mark.parametrize("switch", sorted(INERT_WITHOUT))
def test_a_couplings_settings_act_only_where_it_is_on(switch):
    """The settings `effective_fields` drops where a coupling is off leave three generations'
    state as it was there, and change it where the coupling is on."""
    changes = {name: _CHANGED[name] for name in INERT_WITHOUT[switch]}
    states = {}
    for on in (False, True):
        config = SMALL.replace(**{switch: on})
        pair = (config, config.replace(**changes))
        states[on] = [run(c, seed=0, generations=3)[0] for c in pair]
        fields = [effective_fields(dataclasses.asdict(c)) for c in pair]
        assert (fields[0] == fields[1]) == (not on)
    assert tree_equal(*states[False])
    assert not tree_equal(*states[True])


def tree_equal(a, b):
    return all(bool(jnp.array_equal(x, y, equal_nan=True))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def run(config, seed, generations):
    _, init, step = programs(config)
    state = init(jax.random.PRNGKey(seed))
    history = []
    for _ in range(generations):
        state, metrics = step(state)
        history.append(metrics)
    return state, history


def test_init_fills_buffer_and_centres_cem_on_td3_actor():
    state = programs(SMALL)[1](jax.random.PRNGKey(0))
    assert int(state.total_steps) == 100 and int(state.buffer.size) == 100
    flat_actor = jax.flatten_util.ravel_pytree(state.td3.actor)[0]
    np.testing.assert_array_equal(state.cem.mean, flat_actor)
    np.testing.assert_array_equal(state.cem.elite, flat_actor)


def test_generation_step_is_traced_once():
    traces = []
    agent, init, _ = programs(SMALL)

    def counted(state):
        traces.append(1)
        return agent.generation_step(state)

    step = jax.jit(counted, donate_argnums=0)
    state = init(jax.random.PRNGKey(0))
    for _ in range(4):        # crosses the Q-filter start and a T increase: still one trace
        state, metrics = step(state)
    assert len(traces) == 1
    assert bool(metrics["gen/q_filter_active"]) and int(metrics["gen/episode_limit"]) > 10


def test_same_seed_same_state_different_seed_differs():
    a, history_a = run(SMALL, 3, 3)
    b, history_b = run(SMALL, 3, 3)
    c, _ = run(SMALL, 4, 3)
    assert tree_equal(a, b)
    assert all(tree_equal(x, y) for x, y in zip(history_a, history_b))
    assert not np.array_equal(a.cem.mean, c.cem.mean)
    assert not np.array_equal(a.buffer.data.obs, c.buffer.data.obs)


def test_vmap_over_seeds_equals_separate_runs():
    keys = jax.random.split(jax.random.PRNGKey(11), 3)
    agent, single_init, single_step = programs(SMALL)
    init = jax.jit(jax.vmap(agent.init))
    step = jax.jit(jax.vmap(agent.generation_step))
    batched = init(keys)
    for _ in range(3):
        batched, batched_metrics = step(batched)
    for i in range(3):
        state = single_init(keys[i])
        for _ in range(3):
            state, metrics = single_step(state)
        mine = jax.tree.map(lambda x: x[i], batched)
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5),
                     mine, state)
        assert float(batched_metrics["td3/critic_loss"][i]) == pytest.approx(
            float(metrics["td3/critic_loss"]), rel=1e-4)


def test_the_two_phases_compute_one_generation_step():
    """The trainer's two programs (play, then learn) give what generation_step gives, over
    generations in which an evaluation begins and ends."""
    agent, init, whole = programs(SMALL, evaluated_every(40))       # due every generation
    whole_state = init(jax.random.PRNGKey(3))
    phased_state = jax.tree.map(jnp.copy, whole_state)
    play, learn = jax.jit(agent.play), jax.jit(agent.learn)
    ended = 0
    for _ in range(5):
        whole_state, whole_metrics = whole(whole_state)
        phased_state, phased_metrics = learn(*play(phased_state))
        ended += int(phased_metrics["eval/done"])
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6),
                     (whole_state, whole_metrics), (phased_state, phased_metrics))
    assert ended >= 2


def test_population_layout_and_counters():
    """Resampled from the first generation, so that elitism acts from the first; on this
    key the best actor is not slot 0's, so the elite's return to slot 0 is seen."""
    agent, init, _ = programs(SMALL.replace(resample_before_q_filter=True))
    state = init(jax.random.PRNGKey(2))
    play, learn = jax.jit(agent.play), jax.jit(agent.learn)
    elite_before = np.asarray(state.cem.elite)
    state, played = play(state)
    population = np.asarray(played.population)
    new, metrics = learn(state, played)
    assert int(new.generation) == 1
    assert int(new.total_steps) == 100 + int(metrics["gen/interaction_steps"])
    assert int(new.buffer.size) == int(new.total_steps)
    assert 4 <= int(metrics["gen/interaction_steps"]) <= 4 * 10     # T_init = 10 per actor
    # the rollout lasts as long as its longest episode: the test episodes of the first
    # evaluation, due at once, ride along, the next not falling due for 10k steps
    assert int(metrics["gen/rollout_steps"]) == int(played.episodes.lengths.max())
    # F = 1: the TD3 actor was injected in the last slot and its return is reported
    assert bool(metrics["td3/in_population"])
    assert float(metrics["td3/return"]) == float(metrics["pop/return_3"])
    # elitism: the last elite plays in slot 0; the new elite is the best actor that played
    np.testing.assert_array_equal(population[0], elite_before)
    returns = [float(metrics[f"pop/return_{i}"]) for i in range(SMALL.pop_size)]
    assert int(np.argmax(returns)) != 0
    np.testing.assert_array_equal(np.asarray(new.cem.elite), population[int(np.argmax(returns))])
    assert float(metrics["cem/elite_return"]) == max(returns)
    _, next_played = play(new)
    np.testing.assert_array_equal(np.asarray(next_played.population[0]),
                                  population[int(np.argmax(returns))])


@pytest.mark.parametrize("period", [1, 2])
def test_a_kept_population_plays_until_q_filtering_starts(period):
    """resample_before_q_filter=False (the default, the authors' code): the population drawn
    at the start (μ in slot 0) plays every generation, the TD3 actor in slot N−1 from its first
    turn on, while μ and Σ move; once Q-filtering starts the population is the elite and new
    samples."""
    config = SMALL.replace(resample_before_q_filter=False, td3_to_cem_period=period)
    agent, init, _ = programs(config)
    play, learn = jax.jit(agent.play), jax.jit(agent.learn)
    state = init(jax.random.PRNGKey(0))
    kept = np.asarray(state.kept_population)
    np.testing.assert_array_equal(kept[0], np.asarray(state.cem.mean))
    injected = None
    while int(state.total_steps) < config.q_filter_start:
        state, played = play(state)
        population = np.asarray(played.population)
        n = config.pop_size
        np.testing.assert_array_equal(population[:n - 1], kept[:n - 1])
        if int(state.generation + 1) % period == 0:
            injected = np.asarray(flatten(state.td3.actor))
        np.testing.assert_array_equal(population[n - 1],
                                      kept[n - 1] if injected is None else injected)
        state, _ = learn(state, played)
        assert not np.array_equal(np.asarray(state.cem.mean), kept[0])  # μ still moves
    _, played = play(state)
    population = np.asarray(played.population)
    np.testing.assert_array_equal(population[0], np.asarray(state.cem.elite))
    assert not np.any(np.all(population[1:n - 1, None] == kept[None], axis=-1))


@pytest.mark.parametrize("changes", [
    dict(resample_before_q_filter=True),                    # Algorithm 1 as written
    dict(resample_before_q_filter=False, q_filter=False),   # the authors' code without Q-filter
])
def test_the_population_is_sampled_every_generation(changes):
    """Resampled from the first generation, as Algorithm 1 is written; the authors' code
    keeps its first draws only when run with Q-filtering."""
    config = SMALL.replace(**changes)
    assert not config.keeps_population
    agent, init, _ = programs(config)
    state = init(jax.random.PRNGKey(0))
    assert state.kept_population is None
    play, learn = jax.jit(agent.play), jax.jit(agent.learn)
    state, first = play(state)
    state, _ = learn(state, first)
    _, second = play(state)
    assert not np.any(np.all(np.asarray(second.population)[1:-1, None]
                             == np.asarray(first.population)[None], axis=-1))


def test_base_model_never_injects_or_guides():
    base = SMALL.replace(pg_guides_ea=False, ea_guides_pg=False, q_filter=False,
                         increasing_steps=False)
    _, history = run(base, 0, 3)
    for metrics in history:
        assert not bool(metrics["td3/in_population"]) and not bool(metrics["td3/guided_loss"])
        assert int(metrics["gen/episode_limit"]) == base.t_max
        assert not bool(metrics["gen/q_filter_active"])


def test_ea_guidance_without_injection_probes_the_td3_actor():
    config = SMALL.replace(pg_guides_ea=False, td3_to_cem_period=2)
    _, history = run(config, 0, 4)
    probed = [bool(m["td3/in_population"]) for m in history]
    assert probed == [False, True, False, True]
    assert all(np.isfinite(float(m["td3/return"])) == p for m, p in zip(history, probed))


def test_training_raises_the_return_of_mu():
    config = SMALL.replace(pop_size=6, top_k=3, t_init=50, t_max=50, increasing_steps=False,
                           buffer_size=20_000, warmup_steps=300, q_filter_start=1000,
                           actor_hidden=(32, 32), critic_hidden=(32, 32))
    agent, init, step = programs(config, dataclasses.replace(TESTS, steps=50))
    state = init(jax.random.PRNGKey(0))
    evaluate = jax.jit(agent.evaluate)
    before = float(evaluate(state)["eval/mu_mean"])
    for _ in range(25):
        state, _ = step(state)
    after = evaluate(state)
    # 50 steps at reward 1 − distance: starting near the origin (distance ≈ 1.1) scores ≈ −6;
    # reaching and holding the goal scores > 30.
    assert before < 5.0
    assert float(after["eval/mu_mean"]) > before + 25.0
    assert after["eval/mu_returns"].shape == (3,)


def _check_evaluations(evaluation, seed, generations):
    """Runs `generations` generations. Checks that every evaluation is reported once, in
    order, with exactly what `evaluate` gives for the state it began in, that a generation
    reporting none carries no NaN, and that test episodes are neither stored nor counted.
    Returns [(step, generation reported)] and the steps at which an evaluation fell due while
    another was under way."""
    agent, init, step = programs(SMALL, evaluation, donate=False)
    evaluate = jax.jit(agent.evaluate)
    state = init(jax.random.PRNGKey(seed), jax.random.PRNGKey(seed + 100))
    expected, reported, waited = {}, [], []
    for generation in range(generations):
        tests = state.evaluation
        if int(state.total_steps) >= int(tests.next_due):
            if bool(tests.active):
                waited.append(int(state.total_steps))
            else:
                expected[int(state.total_steps)] = evaluate(state)
        state, metrics = step(state)
        assert all(np.all(np.isfinite(v)) for k, v in metrics.items() if k.startswith("eval/"))
        if bool(metrics["eval/done"]):
            at = int(metrics["eval/step"])
            reported.append((at, generation))
            for name in ("mu", "td3", "elite"):
                np.testing.assert_allclose(metrics[f"eval/{name}_returns"],  # returns near 0
                                           expected[at][f"eval/{name}_returns"],
                                           rtol=1e-5, atol=1e-5)
        assert int(state.buffer.size) == int(state.total_steps)
    steps = [at for at, _ in reported]
    assert steps == sorted(expected)[:len(steps)] and len(steps) == len(set(steps))
    return reported, waited


def test_evaluation_rides_along_and_equals_standalone_evaluate():
    """Test episodes begun when due run alongside later rollouts; the generation in which they
    end reports exactly what `evaluate` gives for the state they began from."""
    # generations of 40-80 steps, tests of 20 steps
    reported, _ = _check_evaluations(evaluated_every(100), 5, 8)
    # begun at the first generation, then once each time the total crosses a multiple of 100
    assert reported[0][0] == 100 and len(reported) >= 3
    crossed = [at // 100 for at, _ in reported]
    assert crossed == list(range(1, len(reported) + 1))
    # the first test (20 steps) outlives the first rollout (10 steps) and ends in the next one
    assert reported[0][1] == 1


def test_no_evaluation_waits_when_its_tests_outlast_a_rollout():
    """Due every generation, tests twice as long as a rollout: each evaluation's episodes
    drive the rollout of the generation it begins in to their end (the next falls due before
    the next rollout), so every generation begins and reports one, from its own state."""
    reported, waited = _check_evaluations(evaluated_every(40, steps=20), 2, 7)
    assert not waited
    assert [generation for _, generation in reported] == list(range(7))
    assert all(later > earlier for (earlier, _), (later, _) in zip(reported, reported[1:]))


def test_evaluate_takes_a_state_or_actors_and_any_kind_of_key():
    """`evaluate(state)` is `evaluate(actors of the state, its evaluation key)`; raw and
    typed (`jax.random.key`) keys both work, in init, generation_step and evaluate."""
    agent = PGPS(SMALL, ENV, TESTS)
    state = jax.jit(agent.init)(jax.random.PRNGKey(3), jax.random.PRNGKey(103))
    by_state = jax.jit(agent.evaluate)(state)
    by_actors = jax.jit(agent.evaluate)(agent.evaluated_actors(state), jax.random.PRNGKey(103))
    jax.tree.map(np.testing.assert_array_equal, by_state, by_actors)
    assert by_state["eval/mu_returns"].shape == (TESTS.episodes,)
    typed = jax.jit(agent.init)(jax.random.key(3), jax.random.key(103))
    typed, metrics = jax.jit(agent.generation_step)(typed)
    assert int(metrics["gen/generation"]) == 1
    assert np.all(np.isfinite(jax.jit(agent.evaluate)(typed)["eval/mu_returns"]))
    with pytest.raises(ValueError, match="key"):
        agent.evaluate(agent.evaluated_actors(state))


def test_evaluate_plays_any_number_of_actors_under_their_names():
    agent = PGPS(SMALL, ENV, TESTS)
    state = jax.jit(agent.init)(jax.random.PRNGKey(3), jax.random.PRNGKey(103))
    three = agent.evaluated_actors(state)
    by_state = agent.evaluate(state)
    key = state.evaluation.key
    one = agent.evaluate(three[:1], key)
    assert set(one) == {"eval/actor0_returns", "eval/actor0_mean", "eval/actor0_std"}
    np.testing.assert_allclose(one["eval/actor0_returns"], by_state["eval/mu_returns"],
                               rtol=1e-6)
    four = agent.evaluate(jnp.concatenate([three, three[2:]]), key)
    np.testing.assert_allclose(four["eval/actor3_returns"], by_state["eval/elite_returns"],
                               rtol=1e-6)
    named = agent.evaluate(three[1:], key, names=("td3", "elite"))
    np.testing.assert_allclose(named["eval/td3_mean"], by_state["eval/td3_mean"], rtol=1e-6)
    with pytest.raises(ValueError, match=r"1 names \('td3',\) for 2 actors"):
        agent.evaluate(three[1:], key, names=("td3",))
    with pytest.raises(ValueError, match=r"\[A, P\], got shape"):
        agent.evaluate(three[0], key)
    with pytest.raises(ValueError, match="distinct non-empty strings, got \\('a', 'a'\\)"):
        agent.evaluate(three[1:], key, names=("a", "a"))
    with pytest.raises(ValueError, match="distinct non-empty strings, got 'ab'"):
        agent.evaluate(three[1:], key, names="ab")
    states = jax.eval_shape(jax.vmap(agent.init), jax.random.split(jax.random.PRNGKey(0), 2))
    with pytest.raises(ValueError, match="one TrainState, not a batch of them: vmap it"):
        agent.evaluate(states)


def test_generation_step_has_no_host_round_trips():
    """One device program per generation: no host callbacks, infeed/outfeed or send/recv."""
    agent, init, step = programs(SMALL)
    state = init(jax.random.PRNGKey(0))
    program = step.lower(state).as_text()
    assert "while" in program                               # the loops stay on the device
    for marker in ("callback", "infeed", "outfeed", "send", "recv", "host"):
        assert marker not in program.lower(), marker

    def leaky(state):       # the check is real: a debug print is a host callback
        jax.debug.print("{}", state.total_steps)
        return agent.generation_step(state)
    assert "callback" in jax.jit(leaky).lower(state).as_text().lower()


def test_the_metrics_are_those_of_the_schema():
    """generation_step reports exactly the metrics that `pgps_jax.agent.metrics` lists."""
    from pgps_jax.agent import metrics as schema
    agent, init, step = programs(SMALL)
    _, metrics = jax.eval_shape(step, jax.eval_shape(init, jax.random.PRNGKey(0)))
    listed = [m.key for m in (*schema.generation_metrics(SMALL.pop_size),
                              *schema.EVALUATION_REPORT,
                              *schema.evaluation_metrics(agent.evaluated))]
    listed += [schema.returns_key(a) for a in ("mu", "td3", "elite")]
    assert len(listed) == len(set(listed)) and set(metrics) == set(listed)


def test_a_state_of_another_env_is_refused_with_the_sizes_that_differ():
    class Wider(PointMass):
        observation_size = property(lambda self: 6)

        def reset(self, rng):
            state = super().reset(rng)
            return state.replace(obs=jnp.zeros(6))

    agent, init, _ = programs(SMALL)
    state = jax.eval_shape(init, jax.random.PRNGKey(0))
    wider = PGPS(SMALL, Wider(), TESTS)
    with pytest.raises(ValueError, match=r"parameter count \d+ \(this agent: \d+\), "
                                         r"observation_size 4 \(this agent: 6\)"):
        jax.eval_shape(wider.generation_step, state)
    with pytest.raises(ValueError, match="parameters but this agent's actor has"):
        jax.eval_shape(wider.evaluate, jax.eval_shape(agent.evaluated_actors, state),
                       jax.random.PRNGKey(0))


@pytest.mark.parametrize("change, field", [
    (dict(critic_hidden=(8, 16)), "td3"), (dict(pop_size=5), "kept_population"),
    (dict(buffer_size=3000), "buffer"), (dict(episodes=2), "evaluation")])
def test_a_state_of_other_sizes_is_refused_naming_the_field(change, field):
    """Any leaf of another shape: other networks, population, buffer or evaluation."""
    config = dataclasses.replace(SMALL, **{k: v for k, v in change.items() if k != "episodes"})
    tests = dataclasses.replace(TESTS, **{k: v for k, v in change.items() if k == "episodes"})
    other = jax.eval_shape(PGPS(config, ENV, tests).init, jax.random.PRNGKey(0))
    agent = PGPS(SMALL, ENV, TESTS)
    with pytest.raises(ValueError, match=rf"other sizes .*\.{field}\b.*\(this agent: "):
        jax.eval_shape(agent.generation_step, other)
    batch = jax.eval_shape(jax.vmap(PGPS(config, ENV, tests).init), jax.random.split(
        jax.random.PRNGKey(0), 3))
    with pytest.raises(ValueError, match=rf"\.{field}\b"):
        agent.check_state(batch)
    agent.check_state(jax.eval_shape(jax.vmap(agent.init), jax.random.split(
        jax.random.PRNGKey(0), 3)))                     # a batch of its own states passes
    agent.check_state(jax.eval_shape(agent.init, jax.random.key(0)))   # typed keys too


def test_the_agent_takes_its_settings_by_the_same_names_and_checks_their_types():
    from pgps_jax.agent.algorithms import make_agent
    assert PGPS(SMALL, ENV, evaluation_config=TESTS).evaluation_config == TESTS
    assert make_agent("pgps", SMALL, ENV, evaluation_config=TESTS).evaluation_config == TESTS
    with pytest.raises(TypeError, match="PGPS's evaluation_config must be of type "
                                        "EvaluationConfig, got dict"):
        PGPS(SMALL, ENV, dict(episodes=2))
    with pytest.raises(TypeError, match="TD3Alone's config must be of type PGPSConfig, got dict"):
        make_agent("td3", {"pop_size": 2}, ENV)


def test_a_state_of_another_algorithm_is_refused_naming_its_fields():
    from pgps_jax.agent.algorithms import make_agent
    td3 = make_agent("td3", SMALL.replace(q_filter=False, pg_guides_ea=False,
                                          ea_guides_pg=False, increasing_steps=False), ENV,
                     TESTS)
    state = jax.eval_shape(td3.init, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"another algorithm or version: fields not this "
                                         r"agent's \[.*\], this agent's fields missing "
                                         r"\['\.beta'"):
        jax.eval_shape(PGPS(SMALL, ENV, TESTS).generation_step, state)

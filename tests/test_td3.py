"""TD3 against hand computations: critic target, soft updates, L^A, β rule, schedule."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from pgps_jax.agent import buffer as replay
from pgps_jax.agent.config import PGPSConfig
from pgps_jax.agent.networks import first_q
from pgps_jax.agent.td3 import TD3, action_distance, adapt_beta, repeat

OBS, ACT, BATCH = 3, 2, 16
CONFIG = PGPSConfig(actor_hidden=(8, 8), critic_hidden=(8, 8), batch_size=BATCH, ss2_size=8)


def elu(x):
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def mlp(layers, x):
    """Numpy forward of a flax Dense stack with ELU between layers."""
    names = sorted(layers, key=lambda name: int(name.split("_")[1]))
    for i, name in enumerate(names):
        x = x @ np.asarray(layers[name]["kernel"]) + np.asarray(layers[name]["bias"])
        if i < len(names) - 1:
            x = elu(x)
    return x


def np_actor(params, obs):
    return np.tanh(mlp(params["params"], obs))


def np_twin_q(params, obs, action):
    heads = params["params"]["Vmap_QHead_0"]
    x = np.concatenate([obs, action], -1)
    return np.stack([mlp(jax.tree.map(lambda p: p[j], heads), x)[..., 0] for j in range(2)])


@pytest.fixture(scope="module")
def setup():
    td3 = TD3(CONFIG, OBS, ACT)
    state = td3.init(jax.random.PRNGKey(0))
    # targets differ from the online networks, as they do after training
    state = state.replace(actor_target=jax.tree.map(lambda p: p * 0.9, state.actor),
                          critic_target=jax.tree.map(lambda p: p * 1.1, state.critic))
    rng = np.random.default_rng(1)
    batch = replay.Transition(
        obs=jnp.asarray(rng.normal(size=(BATCH, OBS)), jnp.float32),
        action=jnp.asarray(rng.uniform(-1, 1, size=(BATCH, ACT)), jnp.float32),
        reward=jnp.asarray(rng.normal(size=BATCH), jnp.float32),
        next_obs=jnp.asarray(rng.normal(size=(BATCH, OBS)), jnp.float32),
        discount=jnp.asarray(rng.integers(0, 2, size=BATCH), jnp.float32))
    return td3, state, batch


def test_critic_target_matches_hand_computation(setup):
    td3, state, batch = setup
    noise = np.asarray(td3.smoothing_noise(jax.random.PRNGKey(7), (BATCH, ACT)))
    next_action = np.clip(np_actor(state.actor_target, np.asarray(batch.next_obs)) + noise, -1, 1)
    q_next = np_twin_q(state.critic_target, np.asarray(batch.next_obs), next_action)
    expected = np.asarray(batch.reward) + 0.99 * np.asarray(batch.discount) * q_next.min(0)
    target_actions = td3.target_actions(state.actor_target, batch.next_obs, jnp.asarray(noise))
    np.testing.assert_allclose(target_actions, next_action, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(td3.critic_targets(state, batch, target_actions), expected,
                               rtol=1e-5, atol=1e-5)


def test_smoothing_noise_is_clipped_gaussian(setup):
    td3, _, _ = setup
    noise = np.asarray(td3.smoothing_noise(jax.random.PRNGKey(0), (20_000,)))
    assert np.abs(noise).max() == pytest.approx(0.5)
    assert np.mean(np.abs(noise) == 0.5) == pytest.approx(0.0124, abs=0.004)  # P(|ε| ≥ 2.5σ)
    assert np.std(noise[np.abs(noise) < 0.5]) == pytest.approx(0.19, abs=0.01)


def test_terminal_transitions_do_not_bootstrap(setup):
    td3, state, batch = setup
    terminal = batch.replace(discount=jnp.zeros(BATCH))
    next_action = td3.target_actions(state.actor_target, batch.next_obs,
                                     td3.smoothing_noise(jax.random.PRNGKey(0), (BATCH, ACT)))
    np.testing.assert_allclose(td3.critic_targets(state, terminal, next_action), batch.reward,
                               rtol=1e-6)


def test_critic_loss_is_sum_of_twin_mse(setup):
    td3, state, batch = setup
    next_action = td3.target_actions(state.actor_target, batch.next_obs,
                                     td3.smoothing_noise(jax.random.PRNGKey(3), (BATCH, ACT)))
    new, loss = td3.critic_update(state, batch, next_action)
    target = np.asarray(td3.critic_targets(state, batch, next_action))
    q = np_twin_q(state.critic, np.asarray(batch.obs), np.asarray(batch.action))
    np.testing.assert_allclose(loss, ((q - target) ** 2).mean(1).sum(), rtol=1e-5)


def test_targets_move_by_exactly_tau(setup):
    td3, state, batch = setup
    new, _ = td3.critic_update(state, batch, jnp.zeros((BATCH, ACT)))
    expected = jax.tree.map(lambda online, old: 0.005 * online + 0.995 * old,
                            new.critic, state.critic_target)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7),
                 new.critic_target, expected)
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.all(a == b)),
                                     new.actor_target, state.actor_target))

    elite_actions = jnp.zeros((BATCH, ACT))
    new, _ = td3.actor_update(state, batch.obs, elite_actions, jnp.asarray(1.0))
    expected = jax.tree.map(lambda online, old: 0.005 * online + 0.995 * old,
                            new.actor, state.actor_target)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7),
                 new.actor_target, expected)


def test_augmented_loss_matches_eq_2(setup):
    td3, state, batch = setup
    obs = np.asarray(batch.obs)
    elite = np.tanh(np.random.default_rng(2).normal(size=(BATCH, ACT))).astype(np.float32)
    actions = np_actor(state.actor, obs)
    q1 = np_twin_q(state.critic, obs, actions)[0]
    for beta in (0.0, 0.5, 4.0):
        expected = -q1.mean() + beta * ((actions - elite) ** 2).mean()
        got = td3.actor_loss(state.actor, state.critic, batch.obs, jnp.asarray(elite),
                             jnp.asarray(beta))
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)


def test_action_distance_is_mean_squared_difference():
    a, b = jnp.array([[0.0, 1.0], [1.0, 1.0]]), jnp.array([[1.0, 1.0], [1.0, -1.0]])
    assert float(action_distance(a, b)) == pytest.approx((1 + 0 + 0 + 4) / 4)


@pytest.mark.parametrize("distance, beta, expected", [
    (0.1, 1.0, 2.0),           # D > 1.5·D_target: double
    (0.076, 1.0, 2.0),
    (0.074, 1.0, 1.0),         # inside [D_target/1.5, 1.5·D_target]: keep
    (0.05, 1.0, 1.0),
    (0.034, 1.0, 1.0),
    (0.033, 1.0, 0.5),         # D < D_target/1.5: halve
    (0.001, 2e-3, 1e-3),       # clamp at beta_min
    (1.0, 1024.0, 1024.0),     # clamp at beta_max
])
def test_beta_rule_eq_3(distance, beta, expected):
    got = adapt_beta(jnp.asarray(beta), jnp.asarray(distance), 0.05, 1e-3, 1024.0)
    assert float(got) == pytest.approx(expected)


def _filled_buffer(rng_seed=0, rows=64):
    rng = np.random.default_rng(rng_seed)
    buf = replay.init(128, OBS, ACT)
    batch = replay.Transition(
        obs=jnp.asarray(rng.normal(size=(rows, OBS)), jnp.float32),
        action=jnp.asarray(rng.uniform(-1, 1, size=(rows, ACT)), jnp.float32),
        reward=jnp.asarray(rng.normal(size=rows), jnp.float32),
        next_obs=jnp.asarray(rng.normal(size=(rows, OBS)), jnp.float32),
        discount=jnp.ones(rows))
    return replay.add(buf, batch, jnp.ones(rows, bool))


def _adam_steps(opt_state) -> int:
    return int(optax.tree_utils.tree_get(opt_state, "count"))


@pytest.mark.parametrize("guided", [False, True])
def test_schedule_runs_blocks_of_num_update(setup, guided):
    td3, state, _ = setup
    buf = _filled_buffer()
    num_update = 3
    new, beta, losses = td3.train(state, buf, jax.random.PRNGKey(0), jnp.asarray(num_update),
                                  4, state.actor, jnp.asarray(guided), jnp.asarray(1.0))
    # 5 blocks × num_update critic and actor updates each
    assert _adam_steps(new.critic_opt) == 5 * num_update
    assert _adam_steps(new.actor_opt) == 5 * num_update
    # elite = the actor itself: D = 0 < D_target/1.5 halves β in each block only when guided
    assert float(beta) == pytest.approx(1.0 / 2 ** 5 if guided else 1.0)
    assert np.isfinite(losses["td3/critic_loss"]) and np.isfinite(losses["td3/actor_loss"])


def test_first_q_is_head_zero_of_the_twin(setup):
    td3, state, batch = setup
    both = td3.critic_net.apply(state.critic, batch.obs, batch.action)
    np.testing.assert_allclose(first_q(td3.critic_net, state.critic, batch.obs, batch.action),
                               both[0], rtol=1e-6)
    assert not np.allclose(both[0], both[1])


def test_unrolled_repeat_equals_plain_loop():
    def body(i, carry):
        return carry * 1.01 + i
    for num in (0, 3, 8, 11):
        plain = jax.lax.fori_loop(0, num, body, jnp.asarray(1.0))
        np.testing.assert_allclose(repeat(jnp.asarray(num), body, jnp.asarray(1.0), 4), plain,
                                   rtol=1e-6)


@pytest.mark.parametrize("beta_adapted", ["before_block", "after_block"])
def test_train_equals_the_updates_one_by_one(setup, beta_adapted):
    """Batched target and elite actions give what per-update forward passes give: π' moves only
    in the actor phase and the elite never, so precomputing them per block changes nothing. β
    is adapted from D on the block's SS_2 before its updates (Algorithm 1) or after them (the
    authors' code)."""
    td3, state, _ = setup
    td3 = TD3(td3.config.replace(beta_adapted=beta_adapted), OBS, ACT)
    buf = _filled_buffer()
    key, num_update, max_update, beta = jax.random.PRNGKey(4), 3, 4, jnp.asarray(0.3)
    elite = td3.init(jax.random.PRNGKey(9)).actor
    new, new_beta, _ = td3.train(state, buf, key, jnp.asarray(num_update), max_update, elite,
                                 jnp.asarray(True), beta)

    reference = state
    for b in range(td3.config.update_blocks):   # Appendix B, written out with its draws
        ss2_key, critic_key, noise_key, actor_key = jax.random.split(jax.random.fold_in(key, b), 4)
        ss2 = replay.sample_obs(buf, ss2_key, td3.config.ss2_size)

        def adapted(beta, actor):
            return adapt_beta(beta, action_distance(td3.actor_net.apply(actor, ss2),
                                                    td3.actor_net.apply(elite, ss2)),
                              0.05, 1e-3, 1024.0)
        if beta_adapted == "before_block":
            beta = adapted(beta, reference.actor)
        critic_rows = replay.random_rows(buf, critic_key, (max_update, td3.config.batch_size))
        noise = td3.smoothing_noise(noise_key, (max_update, td3.config.batch_size, ACT))
        actor_rows = replay.random_rows(buf, actor_key, (max_update, td3.config.batch_size))
        for i in range(num_update):
            batch = replay.gather(buf, critic_rows[i])
            reference, _ = td3.critic_update(
                reference, batch, td3.target_actions(reference.actor_target, batch.next_obs,
                                                     noise[i]))
        for i in range(num_update):
            obs = buf.data.obs[actor_rows[i]]
            reference, _ = td3.actor_update(reference, obs, td3.actor_net.apply(elite, obs), beta)
        if beta_adapted == "after_block":
            beta = adapted(beta, reference.actor)
    assert float(new_beta) == pytest.approx(float(beta))
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5),
                 new, reference)

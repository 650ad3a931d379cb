"""Population episodes: variable lengths, no auto-reset, terminal vs truncation, NaN guard,
and episodes that do not drive the loop carrying on across rollouts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import Env, State

from pgps_jax.agent import buffer as replay
from pgps_jax.agent.rollout import begin_episodes, play, random_warmup, run_episodes


class Countdown(Env):
    """obs = [t, 0]; reward = 1 + action; terminal at step `terminate_at`; NaN at `nan_at`."""

    def __init__(self, terminate_at=1000, nan_at=1000):
        self.terminate_at, self.nan_at = terminate_at, nan_at

    def reset(self, rng):
        zero = jnp.zeros(())
        return State(pipeline_state=None, obs=jnp.zeros(2), reward=zero, done=zero,
                     metrics={"unstable": zero}, info={})

    def step(self, state, action):
        t = state.obs[0] + 1
        obs = jnp.stack([t, jnp.where(t == self.nan_at, jnp.nan, 0.0)])
        done = (t >= self.terminate_at).astype(jnp.float32)
        return state.replace(obs=obs, reward=1.0 + action[0], done=done)

    observation_size = property(lambda self: 2)
    action_size = property(lambda self: 1)
    backend = property(lambda self: "jax")


def constant_policy(params, obs):
    return params[:1]


def run(env, limits, params=None, **kwargs):
    limits = jnp.asarray(limits)
    params = jnp.zeros((limits.size, 1)) if params is None else params
    return run_episodes(env, constant_policy, params, jax.random.split(jax.random.PRNGKey(0),
                        limits.size), limits, max_steps=10, **kwargs)


def test_episodes_stop_at_their_limit_or_termination():
    episodes = run(Countdown(terminate_at=6), [3, 10, 0, 6])
    np.testing.assert_array_equal(episodes.lengths, [3, 6, 0, 6])
    np.testing.assert_array_equal(episodes.returns, [3.0, 6.0, 0.0, 6.0])
    np.testing.assert_array_equal(episodes.valid.sum(0), [3, 6, 0, 6])
    # rows beyond an episode's end are not valid (no auto-reset)
    assert not episodes.valid[6:].any()


def test_terminal_step_has_zero_discount_and_truncation_bootstraps():
    episodes = run(Countdown(terminate_at=4), [10, 3])
    discount = np.asarray(episodes.transitions.discount)
    np.testing.assert_array_equal(discount[:4, 0], [1, 1, 1, 0])   # ends by termination
    np.testing.assert_array_equal(discount[:3, 1], [1, 1, 1])      # cut at T: bootstrap
    np.testing.assert_array_equal(episodes.transitions.next_obs[:4, 0, 0], [1, 2, 3, 4])
    np.testing.assert_array_equal(episodes.transitions.obs[:4, 0, 0], [0, 1, 2, 3])


def test_poisoned_transition_never_reaches_the_buffer():
    episodes = run(Countdown(nan_at=4), [8, 3])
    assert bool(episodes.unstable[0]) and not bool(episodes.unstable[1])
    np.testing.assert_array_equal(episodes.lengths, [4, 3])     # the NaN step ends the episode
    np.testing.assert_array_equal(episodes.returns, [3.0, 3.0])  # and adds no reward
    buffer = replay.add(replay.init(32, 2, 1), episodes.transitions, episodes.valid)
    assert int(buffer.size) == 6
    assert np.isfinite(np.asarray(buffer.data.next_obs)).all()
    assert 4.0 not in np.asarray(buffer.data.next_obs[:, 0])


def test_env_flagged_instability_is_dropped():
    class Flagged(Countdown):
        def step(self, state, action):
            nxt = super().step(state, action)
            return nxt.replace(metrics={"unstable": (nxt.obs[0] == 2).astype(jnp.float32)})
    episodes = run(Flagged(), [5])
    assert int(episodes.lengths[0]) == 2 and int(episodes.valid.sum()) == 1


def test_discounted_return():
    episodes = run(Countdown(), [5], params=jnp.ones((1, 1)), gamma=0.9)  # reward 2 per step
    assert float(episodes.discounted[0]) == np.float32(sum(2 * 0.9 ** t for t in range(5)))
    assert float(episodes.returns[0]) == 10.0


def test_record_false_keeps_only_returns():
    episodes = run(Countdown(), [4, 2], record=False)
    assert episodes.transitions.reward.shape == (0, 2)
    np.testing.assert_array_equal(episodes.returns, [4.0, 2.0])


def test_warmup_restarts_terminated_and_truncated_episodes():
    transitions, valid = random_warmup(Countdown(terminate_at=3), jax.random.PRNGKey(0),
                                       num_envs=2, steps_per_env=7, max_episode_steps=5)
    assert transitions.reward.shape == (7, 2) and bool(valid.all())
    np.testing.assert_array_equal(transitions.obs[:, 0, 0], [0, 1, 2, 0, 1, 2, 0])
    np.testing.assert_array_equal(transitions.discount[:, 0], [1, 1, 0, 1, 1, 0, 1])
    actions = np.asarray(transitions.action)
    assert (np.abs(actions) <= 1).all() and actions.std() > 0.3


def test_warmup_truncates_at_the_time_limit_without_terminal_discount():
    transitions, _ = random_warmup(Countdown(), jax.random.PRNGKey(0), num_envs=1,
                                   steps_per_env=7, max_episode_steps=3)
    np.testing.assert_array_equal(transitions.obs[:, 0, 0], [0, 1, 2, 0, 1, 2, 0])
    np.testing.assert_array_equal(transitions.discount[:, 0], 1)


def test_episodes_that_do_not_drive_the_loop_carry_on_in_the_next_rollout():
    """Slot 0 drives (limit 2, then a fresh one of 3); slot 1 (limit 6) rides along: it is
    left alive after the first rollout and continues where it stopped in the second."""
    env = Countdown()
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    drive = jnp.asarray([True, False])
    params = jnp.asarray([[0.0], [1.0]])        # rewards 1 and 2 a step
    episodes, _, _, loop_steps = play(env, constant_policy, params,
                                      begin_episodes(env, keys, jnp.asarray([2, 6])), 6,
                                      drive=drive)
    np.testing.assert_array_equal(episodes.lengths, [2, 2])
    assert int(loop_steps) == 2  # as long as the episode that drives it
    np.testing.assert_array_equal(episodes.alive, [False, True])
    fresh = begin_episodes(env, keys[:1], jnp.asarray([3]))
    episodes = jax.tree.map(lambda a, b: jnp.concatenate([a, b[1:]]), fresh, episodes)
    episodes, transitions, valid, loop_steps = play(env, constant_policy, params, episodes, 6,
                                                    drive=drive)
    np.testing.assert_array_equal(episodes.lengths, [3, 5])
    assert int(loop_steps) == 3
    np.testing.assert_array_equal(episodes.returns, [3.0, 10.0])
    np.testing.assert_array_equal(transitions.obs[:3, 1, 0], [2, 3, 4])   # from where it was
    np.testing.assert_array_equal(valid.sum(0), [3, 3])


def test_the_loop_counts_its_own_steps_for_each_batch_under_vmap():
    """The loop's steps are its longest driving episode's (a terminal step ends one early);
    vmapped over two batches, each counts its own, though their loop runs for the longer."""
    env = Countdown(terminate_at=4)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    params = jnp.zeros((2, 1))

    def loop_steps(limits):
        return play(env, constant_policy, params, begin_episodes(env, keys, limits), 8,
                    record=False)[3]
    np.testing.assert_array_equal(jax.vmap(loop_steps)(jnp.asarray([[2, 3], [8, 1], [0, 0]])),
                                  [3, 4, 0])


def test_only_the_first_episodes_are_recorded_when_asked():
    """`recorded=1`: the episodes play as before, and the transitions and validity are those
    of the full recording's first slot (the test episodes riding along are not kept)."""
    env = Countdown()
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    params = jnp.asarray([[0.0], [1.0], [2.0]])

    def played(**kwargs):
        return play(env, constant_policy, params, begin_episodes(env, keys, jnp.asarray([4, 6, 5])),
                    6, **kwargs)
    full_episodes, full, full_valid, _ = played()
    episodes, transitions, valid, _ = played(recorded=1)
    equal = lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    jax.tree.map(equal, episodes, full_episodes)
    assert transitions.obs.shape == (6, 1, 2) and valid.shape == (6, 1)
    jax.tree.map(lambda a, b: equal(a, b[:, :1]), transitions, full)
    equal(valid, full_valid[:, :1])
    assert int(valid.sum()) == 4


def test_a_brax_episode_limit_is_a_truncation_not_a_terminal_step():
    """Brax's `EpisodeWrapper` ends an episode at its time limit with done = 1 and
    info["truncation"] = 1: the stored step bootstraps (discount 1), in episodes and in the
    warm-up; a real termination on the same step stays terminal."""
    from brax.envs.wrappers.training import EpisodeWrapper
    for terminate_at, discount in ((1000, 1.0), (3, 0.0)):
        env = EpisodeWrapper(Countdown(terminate_at=terminate_at), episode_length=3,
                             action_repeat=1)
        episodes = run(env, [10])
        assert int(episodes.lengths[0]) == 3
        np.testing.assert_array_equal(episodes.transitions.discount[:3, 0], [1, 1, discount])
        transitions, valid = random_warmup(env, jax.random.PRNGKey(0), 1, 4, 100)
        assert bool(valid[2, 0]) and float(transitions.discount[2, 0]) == discount


class ChangesMetrics(Countdown):
    """A step that adds a metric that reset does not give."""

    def step(self, state, action):
        new = super().step(state, action)
        return new.replace(metrics={**new.metrics, "speed": jnp.zeros(())})


def test_a_step_whose_metrics_differ_from_reset_s_is_named():
    with pytest.raises(ValueError, match=r"metrics keys \['speed', 'unstable'\] but reset "
                                         r"gives \['unstable'\].*new in step: \['speed'\]"):
        run(ChangesMetrics(), [5])


class PoisonedReset(Countdown):
    """Countdown whose reset yields a NaN observation for about half of its keys."""

    def reset(self, rng):
        state = super().reset(rng)
        poisoned = jax.random.bernoulli(rng)
        return state.replace(obs=state.obs.at[1].set(jnp.where(poisoned, jnp.nan, 0.0)))


def test_a_non_finite_observation_from_reset_never_reaches_the_buffer():
    transitions, valid = random_warmup(PoisonedReset(), jax.random.PRNGKey(0), num_envs=8,
                                       steps_per_env=6, max_episode_steps=5)
    poisoned = ~np.isfinite(np.asarray(transitions.obs)).all(-1)
    assert poisoned.any() and (~poisoned).any()      # the reset poisons some episodes only
    np.testing.assert_array_equal(np.asarray(valid), ~poisoned)
    restarted = np.asarray(transitions.obs[1:, :, 0])[poisoned[:-1]]
    np.testing.assert_array_equal(restarted, 0)      # a poisoned start is reset at once
    episodes = run(PoisonedReset(), [4] * 8)
    starts = np.asarray(episodes.transitions.obs[0])
    poisoned = ~np.isfinite(starts).all(-1)
    assert poisoned.any() and (~poisoned).any()
    np.testing.assert_array_equal(np.asarray(episodes.unstable), poisoned)
    np.testing.assert_array_equal(np.asarray(episodes.returns), np.where(poisoned, 0.0, 4.0))
    assert not np.asarray(episodes.valid)[:, poisoned].any()


class Misshapen(Countdown):
    """Countdown whose reset breaks the contract's shapes in one field."""

    def __init__(self, field, shape):
        super().__init__()
        self.field, self.shape = field, shape

    def reset(self, rng):
        state = super().reset(rng)
        return state.replace(**{self.field: jnp.zeros(self.shape)})


@pytest.mark.parametrize("field, shape", [("obs", (1, 2)), ("obs", (3,)), ("reward", (1,)),
                                          ("done", (1,))])
def test_a_reset_of_the_wrong_shapes_is_named(field, shape):
    env = Misshapen(field, shape)
    with pytest.raises(ValueError, match=rf"reset gives {field} of shape \({shape[0]},"):
        random_warmup(env, jax.random.PRNGKey(0), num_envs=2, steps_per_env=3,
                      max_episode_steps=3)
    with pytest.raises(ValueError, match=rf"reset gives {field} of shape"):
        run(env, [2, 2])


def test_an_observation_size_that_the_env_does_not_give_is_named():
    class Declared(Countdown):
        observation_size = property(lambda self: 4)
    with pytest.raises(ValueError, match=r"obs of shape \(2,\) .* needs \(4,\) "
                                         r"\(observation_size 4"):
        run(Declared(), [2])

"""Seeds of a batch that wait a generation out (`loop.Programs(waiting=True)`): a seed's
generations are the same whichever others play beside it, and the runner lets a seed that is
ahead wait (`runner.playing_seeds`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pgps_jax.agent.algorithms import make_agent
from pgps_jax.agent.config import EvaluationConfig, for_task
from pgps_jax.cli import loop
from pgps_jax.envs import make_env
from pgps_jax.experiments.paper import runner

TESTS = EvaluationConfig(every=20, episodes=3, steps=30)  # one falls due every generation
PATTERN = [(1, 1, 1), (1, 0, 1), (0, 0, 1), (1, 1, 0), (0, 1, 1), (1, 1, 1), (1, 0, 0)]
"""Which of three seeds play, generation by generation."""


def agent_of(algo: str):
    config = for_task("hopper", algo, pop_size=4, top_k=2, actor_hidden=(16, 16),
                      critic_hidden=(16, 16), buffer_size=2000, batch_size=32, t_init=10,
                      t_max=20, t_interval=150, t_increment=5,
                      warmup_steps=0 if algo == "cem" else 100)
    return make_agent(algo, config, make_env("point"), TESTS)


def _seed(tree, i):
    return jax.tree.map(lambda x: np.asarray(x[i]), tree)


def _same(a, b) -> None:
    """Equal to float tolerance: the waiting programs are other programs, whose fusions may
    round differently (by about 1e-6 in parameters of order 0.01–0.3 after a few
    generations)."""
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-5)


def _unchanged(a, b) -> None:
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("algo", ["pgps", "cem", "td3", "cemrl"])
def test_a_seed_plays_the_same_generations_whether_others_wait_or_not(algo):
    agent = agent_of(algo)
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(1, 4))
    eval_keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(101, 104))
    lockstep = loop.Programs.compile(agent, keys, eval_keys, seeds=True)
    waiting = loop.Programs.compile(agent, keys, eval_keys, seeds=True, waiting=True)
    episodes = agent.config.exploring_episodes if algo == "td3" else agent.config.pop_size
    assert waiting.generation_steps == episodes * agent.config.t_max

    state = lockstep["init"](keys, eval_keys)
    played = [[_seed(state, i)] for i in range(3)]     # each seed's states, generation by
    reports = [[] for _ in range(3)]                   # generation, and its evaluations
    for _ in range(max(map(sum, zip(*PATTERN)))):
        state, done = loop.generation(lockstep, state)
        for i in range(3):
            played[i].append(_seed(state, i))
            if done.metrics["eval/done"][i]:
                reports[i].append(_seed(done.metrics, i))

    state = waiting["init"](keys, eval_keys)
    generations, ended = [0, 0, 0], [[] for _ in range(3)]
    for active in map(np.array, PATTERN):
        before = [_seed(state, i) for i in range(3)]   # the state itself is donated
        state, done = loop.generation(waiting, state, active=active.astype(bool))
        for i in range(3):
            if active[i]:
                generations[i] += 1
                if done.metrics["eval/done"][i]:
                    ended[i].append(_seed(done.metrics, i))
                assert int(done.metrics["gen/generation"][i]) == generations[i]
            else:  # waited: nothing of its state moved, its buffer included
                _unchanged(_seed(state, i), before[i])
            _same(_seed(state, i), played[i][generations[i]])
    assert generations == [5, 4, 5]
    for i in range(3):
        assert len(ended[i]) >= 2
        _same(ended[i], reports[i][:len(ended[i])])


def test_a_waiting_seed_does_not_hurry_its_evaluation():
    """An evaluation under way whose successor is already due drives the rollout to its end
    (`evaluation.must_end_now`), unless the seed waits: then no episode moves."""
    agent = agent_of("pgps")
    rollout = jax.jit(agent.rollout, static_argnames=("rows",))
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    actors = jnp.stack([agent.evaluated_actors(state)[0]] * 2)
    limits, key = jnp.full((2,), 10), jax.random.PRNGKey(1)
    begun = rollout(state, actors, limits, key, rows=10, active=False)[0]
    assert bool(begun.evaluation.active) and not begun.evaluation.episodes.lengths.any()
    overdue = begun.replace(total_steps=begun.evaluation.next_due)
    waited = rollout(overdue, actors, limits, key, rows=10, active=False)
    played = rollout(overdue, actors, limits, key, rows=10, active=True)
    assert not waited[0].evaluation.episodes.lengths.any() and not waited[1].lengths.any()
    assert (played[0].evaluation.episodes.lengths == TESTS.steps).all()
    assert bool(played[5].done) and not bool(waited[5].done)
    # the hurried test episodes, not the actors' (at most 10 steps), set the rollout's length
    assert int(played[4]) == TESTS.steps > 10 and int(waited[4]) == 0


def test_programs_for_every_seed_refuse_a_choice_of_seeds():
    agent = agent_of("pgps")
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    with pytest.raises(ValueError, match="waiting programs need a batch of seeds"):
        loop.Programs.compile(agent, keys[0], keys[1], waiting=True)


def test_a_seed_ahead_by_more_than_a_generation_or_at_its_budget_waits():
    budget = runner.Budget(steps=10_000, seeds=4)
    steps = np.array([4_000, 5_000, 5_999, 6_001, 4_500])   # the last pads the batch
    np.testing.assert_array_equal(runner.playing_seeds(steps, budget, lead=2_000, seeds=4),
                                  [True, True, True, False, False])
    steps = np.array([10_000, 9_000, 12_000, 9_500, 0])
    np.testing.assert_array_equal(runner.playing_seeds(steps, budget, lead=2_000, seeds=4),
                                  [False, True, False, True, False])
    assert not runner.playing_seeds(np.full(5, 10_000), budget, lead=2_000, seeds=4).any()

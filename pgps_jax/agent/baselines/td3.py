"""TD3 alone (Fujimoto et al., 2018): one actor collects its own experience with Gaussian
noise on its actions and learns from it, with TD3's delayed policy updates.

One generation is one episode of the actor (at most T_max steps, actions
clip(π(s) + N(0, σ²), −1, 1), σ = `exploration_noise`) followed by as many updates as it took
steps (`TD3.train_delayed`), the schedule of the TD3 paper's code; the buffer starts with
`warmup_steps` random-action steps. The actor is reported. With `exploring_episodes` = k > 1
the generation plays k such episodes side by side, each with its own noise, then updates once
per step of all of them.
"""

import dataclasses

import jax
import jax.numpy as jnp

from pgps_jax.agent import buffer as replay
from pgps_jax.agent.base import Agent, Played, TrainState
from pgps_jax.agent.metrics import Metric, chosen
from pgps_jax.agent.networks import flatten

_METRICS = ("gen/generation", "gen/total_steps", "gen/episode_limit", "gen/interaction_steps",
            "gen/rollout_steps", "td3/return", "td3/in_population", "td3/critic_loss",
            "td3/actor_loss", "pop/unstable_episodes")


@dataclasses.dataclass(frozen=True, eq=False)
class TD3Alone(Agent):
    """TD3 learning from its own exploring actor; see the module docstring."""

    name = "td3"
    evaluated = ("td3",)

    def init(self, key: jax.Array, eval_key: jax.Array | None = None) -> TrainState:
        """A fresh actor and twin critic, and a buffer filled by the random warm-up."""
        td3_key, warmup_key, next_key = jax.random.split(key, 3)
        td3_state = self.td3.init(td3_key)
        buffer, total_steps = self.random_warmup(warmup_key)
        actor = flatten(td3_state.actor)
        return TrainState(generation=jnp.zeros((), jnp.int32),
                          total_steps=jnp.asarray(total_steps, jnp.int32),
                          evaluation=self.idle_evaluation(actor[None], key, eval_key),
                          key=next_key, td3=td3_state, buffer=buffer)

    def play(self, state: TrainState, active: jax.Array | bool = True
             ) -> tuple[TrainState, Played]:
        """`exploring_episodes` exploring episodes of the actor, side by side."""
        self.check_state(state)
        config = self.config
        k = config.exploring_episodes
        reset_key, noise_key, train_key, next_key = jax.random.split(state.key, 4)
        actors = jnp.repeat(flatten(state.td3.actor)[None], k, axis=0)
        limit = jnp.asarray(config.t_max, jnp.int32)
        state, episodes, transitions, valid, rollout_steps, report = self.rollout(
            state, actors, jnp.full((k,), limit), reset_key, rows=config.t_max,
            exploration=(noise_key, jnp.full((k,), config.exploration_noise)), active=active)
        return state.replace(key=next_key), Played(
            population=actors, episodes=episodes, transitions=transitions, valid=valid,
            limit=limit, rollout_steps=rollout_steps, td3_turn=jnp.ones((), bool),
            train_key=train_key, evaluation=report)

    def learn(self, state: TrainState, played: Played) -> tuple[TrainState, dict]:
        """The episodes' transitions enter the buffer; as many TD3 updates as they took
        steps."""
        config = self.config
        buffer = replay.add(state.buffer, played.transitions, played.valid)
        steps = played.episodes.lengths.sum()
        td3_state, losses = self.td3.train_delayed(
            state.td3, buffer, played.train_key, steps, config.exploring_episodes * config.t_max)
        new_state = state.replace(td3=td3_state, buffer=buffer,
                                  generation=state.generation + 1,
                                  total_steps=state.total_steps + steps)
        return new_state, {**self.counters_and_evaluation(new_state, played),
                           "td3/return": played.episodes.returns.mean(),
                           "td3/in_population": jnp.ones((), bool), **losses}

    def evaluated_actors(self, state: TrainState) -> jax.Array:
        """[1, P]: the actor."""
        return flatten(state.td3.actor)[None]

    def generation_metrics(self) -> tuple[Metric, ...]:
        return chosen(_METRICS, self.config.pop_size)

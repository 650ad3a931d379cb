"""CEM alone: the diagonal CEM of PGPS searching actor parameters from the population's
episodes, with no critic, no replay buffer and no TD3 actor.

One generation: N actors ~ N(μ, Σ) (slot 0 the last elite with `elitism`) each play one
episode of at most T steps (eq. 4 if `increasing_steps`, else T_max); the CEM update ranks
them by return (`pgps_jax.agent.cem`). μ is reported, as for PGPS.
"""

import dataclasses

import jax
import jax.numpy as jnp

from pgps_jax.agent import cem
from pgps_jax.agent.base import Agent, Played, TrainState
from pgps_jax.agent.config import PGPSConfig
from pgps_jax.agent.metrics import Metric, chosen, population_return_key
from pgps_jax.agent.networks import flatten
from pgps_jax.agent.pgps import episode_limit

_COUNTERS = ("gen/generation", "gen/total_steps", "gen/episode_limit", "gen/interaction_steps",
             "gen/rollout_steps")
_SEARCH = ("pop/return_mean", "pop/return_std", "cem/elite_return", "cem/var_mean",
           "cem/damping")


def search_metrics(pop_size: int, extra: tuple[str, ...] = ()) -> tuple[Metric, ...]:
    """A population search's metrics: the counters, every slot's return, the search
    distribution's, then `extra` and the unstable episodes (CEM alone, CEM-RL)."""
    returns = tuple(population_return_key(i) for i in range(pop_size))
    return chosen(_COUNTERS + returns + _SEARCH + extra + ("pop/unstable_episodes",), pop_size)


def told(config: PGPSConfig, search: cem.CEMState, population: jax.Array,
         returns: jax.Array) -> tuple[cem.CEMState, dict]:
    """The CEM update from the population's returns, and its metrics (`_SEARCH`, every
    slot's return)."""
    new = cem.tell(search, population, returns, top_k=config.top_k,
                   sigma_limit=config.sigma_limit, sigma_decay=config.sigma_decay,
                   divide_by_k=config.cem_divide_by_k)
    return new, {"pop/return_mean": jnp.mean(returns), "pop/return_std": jnp.std(returns),
                 "cem/elite_return": jnp.max(returns), "cem/var_mean": jnp.mean(new.var),
                 "cem/damping": new.damping,
                 **{population_return_key(i): returns[i] for i in range(config.pop_size)}}


def mean_and_elite(state: TrainState) -> jax.Array:
    """[2, P]: μ and the elite (the actors a population search evaluates)."""
    return jnp.stack([state.cem.mean, state.cem.elite])


@dataclasses.dataclass(frozen=True, eq=False)
class CEMAlone(Agent):
    """The CEM over actor parameters; see the module docstring."""

    name = "cem"
    evaluated = ("mu", "elite")

    def init(self, key: jax.Array, eval_key: jax.Array | None = None) -> TrainState:
        """μ = a freshly initialised actor, Σ = Σ_init."""
        actor_key, next_key = jax.random.split(key)
        mean = flatten(self.td3.actor_net.init(actor_key,
                                               jnp.zeros((self.env.observation_size,))))
        return TrainState(generation=jnp.zeros((), jnp.int32),
                          total_steps=jnp.zeros((), jnp.int32),
                          evaluation=self.idle_evaluation(jnp.stack([mean, mean]), key,
                                                          eval_key),
                          key=next_key, cem=cem.init(mean, self.config.sigma_init))

    def play(self, state: TrainState, active: jax.Array | bool = True
             ) -> tuple[TrainState, Played]:
        """N actors sampled from the search distribution play one episode each."""
        self.check_state(state)
        config = self.config
        sample_key, reset_key, next_key = jax.random.split(state.key, 3)
        population = cem.ask(sample_key, state.cem, config.pop_size)
        if config.elitism:
            population = population.at[0].set(state.cem.elite)
        limit = episode_limit(state.total_steps, config)
        state, episodes, transitions, valid, rollout_steps, report = self.rollout(
            state, population, jnp.full((config.pop_size,), limit), reset_key, rows=0,
            record=False, active=active)
        return state.replace(key=next_key), Played(
            population=population, episodes=episodes, transitions=transitions, valid=valid,
            limit=limit, rollout_steps=rollout_steps, td3_turn=jnp.zeros((), bool),
            train_key=next_key, evaluation=report)

    def learn(self, state: TrainState, played: Played) -> tuple[TrainState, dict]:
        """The CEM update from the episodes' returns."""
        new_cem, searched = told(self.config, state.cem, played.population,
                                 played.episodes.returns)
        new_state = state.replace(cem=new_cem, generation=state.generation + 1,
                                  total_steps=state.total_steps
                                  + played.episodes.lengths.sum())
        return new_state, {**self.counters_and_evaluation(new_state, played), **searched}

    def evaluated_actors(self, state: TrainState) -> jax.Array:
        return mean_and_elite(state)

    def generation_metrics(self) -> tuple[Metric, ...]:
        return search_metrics(self.config.pop_size)

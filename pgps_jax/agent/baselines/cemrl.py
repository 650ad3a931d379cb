"""CEM-RL (Pourchot & Sigaud, 2019): the CEM's population, half of it trained by a shared
TD3 critic before it plays, as its authors' code (`es_grad.py`) does.

Each generation: the N actors drawn at the end of the last one play one episode each (T_max
steps) into the buffer; the CEM update ranks them by return; then N actors are drawn for the
next generation and the first N/2 are trained one after the other, each from a copy of itself
as target actor and a fresh Adam: the shared critic first (⌊S/(N/2)⌋ clipped double-Q updates
toward that actor's smoothed target actions, S = this generation's env steps), then the actor
(S updates on −Q1, eq. 1). The buffer starts with `warmup_steps` random-action steps (CEM-RL
plays its first population untrained instead). μ is reported.
"""

import dataclasses

import jax
import jax.numpy as jnp

from pgps_jax.agent import buffer as replay
from pgps_jax.agent import cem
from pgps_jax.agent.base import Agent, Played, TrainState
from pgps_jax.agent.baselines.cem import mean_and_elite, search_metrics, told
from pgps_jax.agent.metrics import Metric
from pgps_jax.agent.networks import flatten
from pgps_jax.agent.td3 import TD3State, repeat


@dataclasses.dataclass(frozen=True, eq=False)
class CEMRL(Agent):
    """CEM-RL with TD3; see the module docstring."""

    name = "cemrl"
    evaluated = ("mu", "elite")

    @property
    def num_trained(self) -> int:
        """The actors of a population that the critic trains: the first N/2."""
        return self.config.pop_size // 2

    def init(self, key: jax.Array, eval_key: jax.Array | None = None) -> TrainState:
        """A fresh twin critic, μ = a fresh actor, the warm-up's buffer and a first,
        untrained population."""
        td3_key, warmup_key, sample_key, next_key = jax.random.split(key, 4)
        td3_state = self.td3.init(td3_key)
        buffer, total_steps = self.random_warmup(warmup_key)
        mean = flatten(td3_state.actor)
        search = cem.init(mean, self.config.sigma_init)
        return TrainState(generation=jnp.zeros((), jnp.int32),
                          total_steps=jnp.asarray(total_steps, jnp.int32),
                          evaluation=self.idle_evaluation(jnp.stack([mean, mean]), key,
                                                          eval_key),
                          key=next_key, cem=search, td3=td3_state, buffer=buffer,
                          next_population=self.sample(sample_key, search))

    def sample(self, key: jax.Array, search: cem.CEMState) -> jax.Array:
        """N actors ~ N(μ, Σ) (slot 0 the elite with `elitism`): [N, P]."""
        population = cem.ask(key, search, self.config.pop_size)
        return population.at[0].set(search.elite) if self.config.elitism else population

    def play(self, state: TrainState, active: jax.Array | bool = True
             ) -> tuple[TrainState, Played]:
        """The population drawn (and half trained) at the end of the last generation plays."""
        self.check_state(state)
        config = self.config
        reset_key, train_key, next_key = jax.random.split(state.key, 3)
        population = state.next_population
        limit = jnp.asarray(config.t_max, jnp.int32)
        state, episodes, transitions, valid, rollout_steps, report = self.rollout(
            state, population, jnp.full((config.pop_size,), limit), reset_key,
            rows=config.t_max, active=active)
        return state.replace(key=next_key), Played(
            population=population, episodes=episodes, transitions=transitions, valid=valid,
            limit=limit, rollout_steps=rollout_steps, td3_turn=jnp.zeros((), bool),
            train_key=train_key, evaluation=report)

    def learn(self, state: TrainState, played: Played) -> tuple[TrainState, dict]:
        """Buffer, CEM update, then the next population with its first half trained."""
        config = self.config
        buffer = replay.add(state.buffer, played.transitions, played.valid)
        steps = played.episodes.lengths.sum()
        new_cem, searched = told(config, state.cem, played.population, played.episodes.returns)
        sample_key, train_key = jax.random.split(played.train_key)
        population = self.sample(sample_key, new_cem)
        td3_state, trained, losses = self.train_half(state.td3, buffer, train_key,
                                                     population[:self.num_trained], steps)
        new_state = state.replace(cem=new_cem, td3=td3_state, buffer=buffer,
                                  generation=state.generation + 1,
                                  total_steps=state.total_steps + steps,
                                  next_population=population.at[:self.num_trained]
                                  .set(trained))
        return new_state, {**self.counters_and_evaluation(new_state, played), **searched,
                           **losses}

    def train_half(self, td3_state: TD3State, buffer: replay.BufferState, key: jax.Array,
                   actors: jax.Array, steps: jax.Array
                   ) -> tuple[TD3State, jax.Array, dict]:
        """Trains `actors` [N/2, P] as if one after the other with the shared critic (see the
        module docstring); returns the critic's state, the trained actors and mean losses.

        An actor's S updates move only that actor and its target, never the critic, so the
        critic's blocks run in sequence first, each keeping the critic it ends with, and the
        N/2 actors then train side by side, each against its own block's critic: the same
        updates as one after the other, in N/2-fold fewer sequential steps."""
        td3, c = self.td3, self.config
        critic_updates = steps // self.num_trained
        keys = jax.vmap(lambda k: jax.random.split(k, 3))(
            jax.random.split(key, self.num_trained))       # [N/2, 3]: batch, noise, obs

        def critic_block(carry, inputs):
            td3_state, total = carry
            flat, (batch_key, noise_key, _) = inputs
            actor_target = self._unflatten(flat)            # a copy of the actor to train

            def critic_step(j, carry):
                td3_state, total = carry
                batch = replay.sample(buffer, jax.random.fold_in(batch_key, j), c.batch_size)
                noise = td3.smoothing_noise(jax.random.fold_in(noise_key, j),
                                            (c.batch_size, td3.action_size))
                next_action = td3.target_actions(actor_target, batch.next_obs, noise)
                td3_state, loss = td3.critic_update(td3_state, batch, next_action)
                return td3_state, total + loss

            td3_state, total = repeat(critic_updates, critic_step, (td3_state, total),
                                      c.update_unroll)
            return (td3_state, total), td3_state.critic

        zero = jnp.zeros((), jnp.float32)
        (td3_state, critic_total), critics = jax.lax.scan(critic_block, (td3_state, zero),
                                                         (actors, keys))

        def train_actor(flat, critic, actor_keys):
            actor = self._unflatten(flat)
            state = td3_state.replace(critic=critic, actor=actor, actor_target=actor,
                                      actor_opt=td3.actor_optimizer.init(actor))

            def actor_step(j, carry):
                state, total = carry
                obs = replay.sample_obs(buffer, jax.random.fold_in(actor_keys[2], j),
                                        c.batch_size)
                state, loss = td3.actor_update(
                    state, obs, jnp.zeros((c.batch_size, td3.action_size)), jnp.zeros(()))
                return state, total + loss

            state, total = repeat(steps, actor_step, (state, zero), c.update_unroll)
            return state.actor, state.actor_target, state.actor_opt, total

        actor, actor_target, actor_opt, actor_totals = jax.vmap(train_actor)(actors, critics,
                                                                             keys)
        td3_state = td3_state.replace(**jax.tree.map(      # as the last actor trained left it
            lambda x: x[-1], dict(actor=actor, actor_target=actor_target, actor_opt=actor_opt)))
        return td3_state, jax.vmap(flatten)(actor), {
            "td3/critic_loss": critic_total / jnp.maximum(critic_updates * self.num_trained, 1),
            "td3/actor_loss": actor_totals.sum() / jnp.maximum(steps * self.num_trained, 1)}

    def evaluated_actors(self, state: TrainState) -> jax.Array:
        return mean_and_elite(state)

    def generation_metrics(self) -> tuple[Metric, ...]:
        return search_metrics(self.config.pop_size, ("td3/critic_loss", "td3/actor_loss"))

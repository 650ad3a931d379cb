"""PGPS (Algorithm 1) as one agent object: `PGPS(config, env)` with pure `init`,
`generation_step` and `evaluate` (`pgps_jax.agent.base.Agent`) over the `TrainState` pytree.

Everything that changes lives in the TrainState; the configuration, the env and the networks
are held by the agent, so `agent.generation_step(state)` is one pure function that the caller
jits (state donated), vmaps over a batch of states (seeds) or scans over generations.

One generation (Algorithm 1, lines 6-37):
 1. population: slot 0 = elite, the rest ~ N(μ, Σ) (by default, as the authors' code runs
    it, the population drawn at the start until Q-filtering starts:
    `resample_before_q_filter`); after T_start-Q total steps the slots
    [N/2, N) are the best of SR·N samples by the critic (Algorithm 2); every F generations the
    TD3 actor takes slot N−1 (PG→EA).
 2. every actor plays one episode of at most T steps (eq. 4); real transitions enter the buffer.
 3. CEM update with the returns (maximised); elite = best actor of this generation.
 4. TD3 trains for as many updates as the generation's env steps, in 5 blocks; if the TD3 actor
    fell behind (return < the population's mean, as the authors' code computes it; mean − std
    in Algorithm 1: `fell_behind_rule`), with the augmented loss toward the elite and an
    adaptive β (EA→PG, eq. 2-3), adapted before each block's updates as in Algorithm 1
    (after them in the authors' code: `beta_adapted`); its target actor follows it alone, as
    in Algorithm 3 (the authors' code first sets it to the elite: `target_actor_from_elite`).

The test evaluation (Section 5.1, `pgps_jax.agent.evaluation`) rides along in the population's
rollouts: when it falls due, the generation snapshots μ, the TD3 actor and the elite and their
test episodes advance in extra slots of every rollout until they have all ended, when the
generation reports them (`eval/done`).
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp

from pgps_jax.agent import buffer as replay
from pgps_jax.agent import cem, qfilter
from pgps_jax.agent.base import Agent, Played, TrainState
from pgps_jax.agent.config import PGPSConfig
from pgps_jax.agent.couplings import Couplings
from pgps_jax.agent.metrics import Metric, generation_metrics, population_return_key
from pgps_jax.agent.networks import first_q, flatten
from pgps_jax.agent.td3 import TD3State

PHASES = ("population_generation", "actors_evaluation", "cem_update", "td3_update")
"""The parts of a generation whose computational time Table 1 of the paper splits, as JAX
named scopes of the programs' operations (metadata only: they change nothing computed)."""


def episode_limit(total_steps: jax.Array, config: PGPSConfig,
                  increasing: bool | jax.Array | None = None) -> jax.Array:
    """Eq. 4 with floor division: T = min(T_init + 100·⌊steps / T_interval⌋, T_max); T_max
    without increasing steps (`increasing`, by default the configuration's)."""
    increasing = config.increasing_steps if increasing is None else increasing
    if increasing is False:
        return jnp.asarray(config.t_max, jnp.int32)
    grown = config.t_init + config.t_increment * (total_steps // config.t_interval)
    limit = jnp.minimum(grown, config.t_max).astype(jnp.int32)
    return limit if increasing is True else jnp.where(increasing, limit, config.t_max)


def fell_behind(td3_return: jax.Array, population_returns: jax.Array, rule: str
                ) -> jax.Array:
    """The TD3 actor lags (`FELL_BEHIND_RULES`): Return_TD3 < mean of the generation's
    returns with rule="mean" (the authors' code), < mean − std with "mean_minus_std"
    (Algorithm 1)."""
    threshold = jnp.mean(population_returns)
    if rule == "mean_minus_std":
        threshold = threshold - jnp.std(population_returns)
    return td3_return < threshold


@dataclasses.dataclass(frozen=True, eq=False)
class PGPS(Agent):
    """The algorithm bound to a configuration, an env and the test evaluation's settings; its
    methods are pure. jit, vmap, donation and sharding are the caller's choice:

        agent = PGPS(for_task("hopper"), make_env("hopper"))
        state = jax.jit(agent.init)(jax.random.key(0))
        step = jax.jit(agent.generation_step, donate_argnums=0)
        state, metrics = step(state)

    The env is any Brax `Env` (`brax.envs.base.Env`) that keeps this contract:
    - unbatched: `reset(key)` and `step(state, action)` act on one episode (PGPS vmaps them);
    - `obs` is a flat vector of `observation_size`, `reward` and `done` scalars (a reset of
      other shapes raises ValueError naming the field);
    - `step` takes actions in [-1, 1]^`action_size` as they are (a physics whose state has
      controls, `pipeline_state.ctrl`, has `action_size` of them, else ValueError);
    - `reset` and `step` give states of the same structure: the same `metrics` and `info`
      keys, arrays of the same shapes and dtypes (a mismatch raises ValueError naming them);
    - `done` (any numeric dtype) ends an episode, as terminal unless `info["truncation"]` is
      set (Brax's `EpisodeWrapper` time limit), when the critic bootstraps through it;
    - optional `metrics["unstable"]` > 0 ends an episode whose step is kept out of the
      replay buffer, as is any step with a non-finite observation or reward.
    No time limit is needed: PGPS caps every episode (eq. 4, `PGPSConfig.t_max`).
    """

    name = "pgps"
    evaluated = ("mu", "td3", "elite")
    """μ, the TD3 actor and the elite; μ is reported."""

    # --- init -------------------------------------------------------------------------
    def init(self, key: jax.Array, eval_key: jax.Array | None = None,
             couplings: Couplings | None = None) -> TrainState:
        """Fresh TD3, μ = the TD3 actor's parameters, and a buffer filled by the random
        warm-up.

        eval_key: start states of every evaluation (the paper uses seed + 100); by default
        derived from `key`. The first generation evaluates the initial μ.
        couplings: the state's own switches of the couplings (`couplings.couplings_of`: one of
        Table 1's models); by default the configuration's.
        """
        config = self.config
        td3_key, warmup_key, next_key = jax.random.split(key, 3)
        td3_state = self.td3.init(td3_key)
        buffer, total_steps = self.random_warmup(warmup_key)
        mean = flatten(td3_state.actor)
        search = cem.init(mean, config.sigma_init)
        kept = (cem.ask(jax.random.fold_in(key, 1), search, config.pop_size).at[0].set(mean)
                if config.keeps_population else None)
        return TrainState(cem=search,
                          td3=td3_state, buffer=buffer,
                          beta=jnp.asarray(config.beta_init, jnp.float32),
                          generation=jnp.zeros((), jnp.int32),
                          total_steps=jnp.asarray(total_steps, jnp.int32),
                          evaluation=self.idle_evaluation(
                              jnp.stack([mean] * len(self.evaluated)), key, eval_key),
                          key=next_key, kept_population=kept, couplings=couplings)

    # --- one generation ---------------------------------------------------------------
    def play(self, state: TrainState, active: jax.Array | bool = True
             ) -> tuple[TrainState, Played]:
        """Algorithm 1 lines 6-18: the generation's actors and their episodes, with the test
        episodes of the evaluation under way alongside.

        Returns `state` with its evaluation advanced (and its key), and the episodes for
        `learn`. `active` False: no episode plays a step (`Agent.play`).
        """
        self.check_state(state)
        config = self.config
        (sample_key, candidate_key, states_key, reset_key, train_key,
         next_key) = jax.random.split(state.key, 6)
        n = config.pop_size
        td3_turn = ((state.generation + 1) % config.td3_to_cem_period) == 0

        with jax.named_scope("population_generation"):
            population = self.generated_population(state, sample_key, candidate_key,
                                                   states_key, td3_turn)
        if state.kept_population is not None:
            state = state.replace(kept_population=population)  # with the injected TD3 actor
        limit = episode_limit(state.total_steps, config,
                              self.switch(state, "increasing_steps"))
        actors, limits = population, jnp.full((n,), limit)
        if config.td3_probe:
            actors = jnp.concatenate([population, flatten(state.td3.actor)[None]])
            limits = jnp.append(limits, jnp.where(td3_turn, limit, 0))
        with jax.named_scope("actors_evaluation"):
            state, episodes, transitions, valid, rollout_steps, report = self.rollout(
                state, actors, limits, reset_key, rows=config.t_max, active=active)
        state = state.replace(key=next_key)
        return state, Played(population=population, episodes=episodes,
                             transitions=transitions, valid=valid, limit=limit,
                             rollout_steps=rollout_steps, td3_turn=td3_turn, train_key=train_key,
                             evaluation=report)

    def learn(self, state: TrainState, played: Played) -> tuple[TrainState, dict]:
        """Algorithm 1 lines 19-37: the buffer takes the episodes' transitions, CEM ranks the
        population, TD3 trains (with L^A toward the elite if its actor fell behind). Returns
        the next state and the generation's metrics (`pgps_jax.agent.metrics`: per
        generation, and `eval/*` for a test evaluation, holding its results where
        `eval/done`)."""
        config = self.config
        n = config.pop_size
        episodes, td3_turn = played.episodes, played.td3_turn
        interaction_steps = episodes.lengths.sum()

        returns = episodes.returns[:n]
        with jax.named_scope("cem_update"):
            new_cem = self.cem_update(state.cem, played.population, returns)
        pg_guides_ea = self.switch(state, "pg_guides_ea")
        ea_guides_pg = self.switch(state, "ea_guides_pg")
        td3_in_episodes = pg_guides_ea | config.td3_probe
        td3_return = self._td3_return(episodes.returns, pg_guides_ea)
        if ea_guides_pg is False:
            guided = jnp.zeros((), bool)
        else:
            guided = (td3_turn & fell_behind(td3_return, returns, config.fell_behind_rule)
                      & ea_guides_pg)
        with jax.named_scope("td3_update"):
            buffer, new_td3, beta, losses = self.td3_update(
                state, played, self._unflatten(new_cem.elite), guided)
        generation = state.generation + 1
        new_state = state.replace(cem=new_cem, td3=new_td3, buffer=buffer, beta=beta,
                                  generation=generation,
                                  total_steps=state.total_steps + interaction_steps)
        metrics = {
            **self.counters_and_evaluation(new_state, played),
            "gen/q_filter_active": ((state.total_steps >= config.q_filter_start)
                                    & self.switch(state, "q_filter")),
            "pop/return_mean": jnp.mean(returns),
            "pop/return_std": jnp.std(returns),
            "cem/elite_return": jnp.max(returns),
            "cem/var_mean": jnp.mean(new_cem.var),
            "cem/damping": new_cem.damping,
            "td3/in_population": td3_turn & td3_in_episodes,
            "td3/return": jnp.where(td3_turn, td3_return, jnp.nan),
            "td3/guided_loss": guided,
            "td3/beta": beta,
            **{population_return_key(i): returns[i] for i in range(n)},
            **losses,
        }
        return new_state, metrics

    # --- three phases of a generation (`PHASES`; actors evaluation is `rollout`) ---------
    def generated_population(self, state: TrainState, sample_key: jax.Array,
                             candidate_key: jax.Array, states_key: jax.Array,
                             td3_turn: jax.Array) -> jax.Array:
        """Algorithm 1 lines 6-13: the N actors to evaluate (`population`), the TD3 actor in
        slot N−1 at its turn, every F generations, where PG→EA is on."""
        population = self.population(state, sample_key, candidate_key, states_key)
        pg_guides_ea = self.switch(state, "pg_guides_ea")
        if pg_guides_ea is False:
            return population
        injected = population.at[self.config.pop_size - 1].set(flatten(state.td3.actor))
        return jnp.where(td3_turn & pg_guides_ea, injected, population)

    def cem_update(self, search: cem.CEMState, population: jax.Array, returns: jax.Array
                   ) -> cem.CEMState:
        """Algorithm 1 line 23: the elite, μ and Σ from the top-K actors by return."""
        config = self.config
        return cem.tell(search, population, returns, top_k=config.top_k,
                        sigma_limit=config.sigma_limit, sigma_decay=config.sigma_decay,
                        divide_by_k=config.cem_divide_by_k)

    def td3_update(self, state: TrainState, played: Played, elite, guided: jax.Array
                   ) -> tuple[replay.BufferState, TD3State, jax.Array, dict]:
        """Algorithm 1 lines 19 and 24-37: the buffer takes the episodes' transitions, then
        TD3 trains as many updates as the generation's env steps, on L^A toward `elite` (the
        actor's parameters) where `guided` (eq. 2-3), its target actor first set to `elite`
        with `target_actor_from_elite`. Returns the buffer, the TD3 state, β and the
        losses."""
        config = self.config
        buffer = replay.add(state.buffer, played.transitions, played.valid)
        lengths = played.episodes.lengths
        num_update = lengths.sum() // config.update_blocks
        max_update = lengths.shape[0] * config.t_max // config.update_blocks
        td3_state = state.td3
        if config.target_actor_from_elite:
            td3_state = td3_state.replace(actor_target=elite)
        td3_state, beta, losses = self.td3.train(td3_state, buffer, played.train_key,
                                                 num_update, max_update, elite, guided,
                                                 state.beta)
        return buffer, td3_state, beta, losses

    def generation_metrics(self) -> tuple[Metric, ...]:
        return generation_metrics(self.config.pop_size)

    def population(self, state: TrainState, sample_key: jax.Array, candidate_key: jax.Array,
                    states_key: jax.Array) -> jax.Array:
        """Algorithm 1 lines 6-10 and Algorithm 2: the N actors to evaluate, [N, P] (the
        population kept from the start until Q-filtering starts, if the state keeps one)."""
        config = self.config
        n, half = config.pop_size, config.pop_size // 2
        population = cem.ask(sample_key, state.cem, n)
        if config.elitism:
            population = population.at[0].set(state.cem.elite)
        q_filter = self.switch(state, "q_filter")
        if state.kept_population is not None:  # kept by a state that Q-filters, until it does
            resampled = state.total_steps >= config.q_filter_start
            if q_filter is not True:
                resampled = resampled | jnp.logical_not(q_filter)
            population = jnp.where(resampled, population, state.kept_population)
        if q_filter is False:
            return population

        def filtered(population):
            candidates = cem.ask(candidate_key, state.cem, config.num_candidates)
            states = replay.sample_obs(state.buffer, states_key, config.ss1_size)
            q1 = functools.partial(first_q, self.td3.critic_net)
            scores = qfilter.potentials(self.policy, q1, candidates, state.td3.critic, states)
            return population.at[half:].set(
                qfilter.select_best(candidates, scores, config.num_elite_filtered))

        return jax.lax.cond((state.total_steps >= config.q_filter_start) & q_filter, filtered,
                            lambda population: population, population)

    def switch(self, state: TrainState, coupling: str) -> bool | jax.Array:
        """Whether `coupling` (`config.SWITCHES`) is on: the configuration's, a Python bool,
        or the state's own, a bool array, where it carries `Couplings`."""
        if state.couplings is None:
            return bool(getattr(self.config, coupling))
        return jnp.asarray(getattr(state.couplings, coupling), bool)

    def _td3_return(self, returns: jax.Array, pg_guides_ea: bool | jax.Array) -> jax.Array:
        """The TD3 actor's return: slot N−1 (PG→EA), the probe slot N, or NaN where it never
        plays."""
        config = self.config
        if pg_guides_ea is True:
            return returns[config.pop_size - 1]
        if config.td3_probe:  # a state's PG→EA is off where the probe is (`couplings_of`)
            return returns[config.pop_size]
        if pg_guides_ea is False:
            return jnp.asarray(jnp.nan)
        return jnp.where(pg_guides_ea, returns[config.pop_size - 1], jnp.nan)

    # --- evaluation -------------------------------------------------------------------
    def evaluated_actors(self, state: TrainState) -> jax.Array:
        """[3, P]: μ, the TD3 actor and the elite."""
        return jnp.stack([state.cem.mean, flatten(state.td3.actor), state.cem.elite])

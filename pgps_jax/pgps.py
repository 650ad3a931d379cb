"""PGPS: TrainState, init, generation_step and evaluate (Algorithm 1).

Everything that changes lives in one TrainState pytree; the configuration and the env are
static and bound by the `make_*` factories, so `generation_step(state)` is one pure function
that can be jitted once (state donated) or vmapped over a batch of states (seeds).

One generation (Algorithm 1, lines 6-37):
 1. population: slot 0 = elite, the rest ~ N(μ, Σ); after T_start-Q total steps the slots
    [N/2, N) are the best of SR·N samples by the critic (Algorithm 2); every F generations the
    TD3 actor takes slot N−1 (PG→EA).
 2. every actor plays one episode of at most T steps (eq. 4); real transitions enter the buffer.
 3. CEM update with the returns (maximised); elite = best actor of this generation.
 4. TD3 trains for as many updates as the generation's env steps, in 5 blocks; if the TD3 actor
    fell behind (return < mean − std of the population), with the augmented loss toward the
    elite and an adaptive β (EA→PG, eq. 2-3).

Test evaluation (Section 5.1) rides along: when `eval_every` env steps have passed, the
generation snapshots μ, the TD3 actor and the elite and starts their test episodes in the same
batch as the population's rollout. They advance with every later rollout — adding no
sequential env steps — and their returns are reported by the first generation that ends with
them ended. If the previous evaluation is still under way when the next falls due, the next
one is queued: its episodes take over the test slots inside the rollout, in the step after the
previous one's last episode ends (every evaluation starts from the same states, so when it
starts changes none of its returns). A rollout runs on past its population only when an
evaluation is queued and another could fall due before the next generation.
"""

import functools
from typing import Callable

import chex
import jax
import jax.numpy as jnp

from pgps_jax import buffer as replay
from pgps_jax import cem, qfilter
from pgps_jax.config import EVALUATED_ACTORS, PGPSConfig
from pgps_jax.envs import Env
from pgps_jax.networks import actor_flattener, first_q, flatten
from pgps_jax.rollout import (EpisodeState, Relay, begin_episodes, play, random_warmup,
                              run_episodes)
from pgps_jax.td3 import TD3, TD3State


@chex.dataclass(frozen=True)
class EvaluationState:
    """The test episodes under way (Section 5.1) and the evaluation queued behind them,
    carried from generation to generation."""
    episodes: EpisodeState       # [A·E] episodes of the actors, E per actor, in EVALUATED order
    actors: jax.Array            # [A, P] the actors as they were when the evaluation fell due
    step: jax.Array              # [] int32 total_steps when it fell due
    active: jax.Array            # [] bool, begun and not yet reported
    queued_actors: jax.Array     # [A, P] the next evaluation's actors, waiting for the slots
    queued_step: jax.Array       # [] int32 total_steps when it fell due
    queued: jax.Array            # [] bool, an evaluation is queued


@chex.dataclass(frozen=True)
class TrainState:
    cem: cem.CEMState            # μ, Σ, damping, elite (flat actor vectors [P])
    td3: TD3State                # actor, twin critic, targets, optimiser states
    buffer: replay.BufferState   # device replay buffer
    beta: jax.Array              # [] distance weight β of L^A (eq. 2-3), persists
    generation: jax.Array        # [] int32 generations completed
    total_steps: jax.Array       # [] int32 env steps so far, warm-up included
    next_eval: jax.Array         # [] int32 total_steps at which the next evaluation is due
    evaluation: EvaluationState  # the test episodes under way
    key: jax.Array               # PRNG key
    eval_key: jax.Array          # PRNG key of the fixed evaluation start states


def episode_limit(total_steps: jax.Array, config: PGPSConfig) -> jax.Array:
    """Eq. 4 with floor division: T = min(T_init + 100·⌊steps / T_interval⌋, T_max)."""
    if not config.increasing_steps:
        return jnp.asarray(config.t_max, jnp.int32)
    grown = config.t_init + config.t_increment * (total_steps // config.t_interval)
    return jnp.minimum(grown, config.t_max).astype(jnp.int32)


def fell_behind(td3_return: jax.Array, population_returns: jax.Array,
                rule: str = "mean_minus_std") -> jax.Array:
    """The TD3 actor lags: Return_TD3 < mean − std of the generation's returns (Algorithm 1),
    or < mean with rule="mean" (the authors' code)."""
    threshold = jnp.mean(population_returns)
    if rule == "mean_minus_std":
        threshold = threshold - jnp.std(population_returns)
    return td3_return < threshold


def _policy(td3: TD3, unflatten: Callable) -> Callable:
    """(flat actor vector, obs) -> action."""
    return lambda flat, obs: td3.actor_net.apply(unflatten(flat), obs)


def actor_policy(config: PGPSConfig, env: Env) -> Callable:
    """The deterministic policy of a flat actor vector: (flat, obs) -> action."""
    return _policy(*_parts(config, env))


def _parts(config: PGPSConfig, env: Env) -> tuple[TD3, Callable]:
    td3 = TD3(config, env.observation_size, env.action_size)
    _, unflatten = actor_flattener(td3.actor_net, env.observation_size)
    return td3, unflatten


def init(config: PGPSConfig, env: Env, key: jax.Array,
         eval_key: jax.Array | None = None) -> TrainState:
    """Fresh TD3, μ = the TD3 actor's parameters, and a buffer filled by the random warm-up.

    eval_key: start states of every evaluation (the paper uses seed + 100); by default derived
    from `key`. The first generation evaluates the initial μ.
    """
    td3, _ = _parts(config, env)
    td3_key, warmup_key, next_key = jax.random.split(key, 3)
    td3_state = td3.init(td3_key)
    buffer = replay.init(config.buffer_size, env.observation_size, env.action_size)
    total_steps = 0
    if config.warmup_steps > 0:
        steps_per_env = -(-config.warmup_steps // config.pop_size)
        transitions, valid = random_warmup(env, warmup_key, config.pop_size, steps_per_env,
                                           config.t_max)
        buffer = replay.add(buffer, transitions, valid)
        total_steps = steps_per_env * config.pop_size
    eval_key = jax.random.fold_in(key, 100) if eval_key is None else eval_key
    mean = flatten(td3_state.actor)
    actors, zero = jnp.stack([mean] * len(EVALUATED)), jnp.zeros((), jnp.int32)
    idle = EvaluationState(episodes=_test_episodes(config, env, eval_key, steps=0),
                           actors=actors, step=zero, active=jnp.asarray(False),
                           queued_actors=actors, queued_step=zero, queued=jnp.asarray(False))
    return TrainState(cem=cem.init(mean, config.sigma_init),
                      td3=td3_state, buffer=buffer,
                      beta=jnp.asarray(config.beta_init, jnp.float32),
                      generation=jnp.zeros((), jnp.int32),
                      total_steps=jnp.asarray(total_steps, jnp.int32),
                      next_eval=jnp.zeros((), jnp.int32),
                      evaluation=idle,
                      key=next_key, eval_key=eval_key)


def _population(config: PGPSConfig, td3: TD3, unflatten: Callable, state: TrainState,
                sample_key: jax.Array, candidate_key: jax.Array,
                states_key: jax.Array) -> jax.Array:
    """Algorithm 1 lines 6-10 and Algorithm 2: the N actors to evaluate, [N, P]."""
    n, half = config.pop_size, config.pop_size // 2
    population = cem.ask(sample_key, state.cem, n).at[0].set(state.cem.elite)
    if not config.q_filter:
        return population

    def filtered(population):
        candidates = cem.ask(candidate_key, state.cem, config.num_candidates)
        states = replay.sample_obs(state.buffer, states_key, config.ss1_size)
        q1 = functools.partial(first_q, td3.critic_net)
        scores = qfilter.potentials(_policy(td3, unflatten), q1, candidates,
                                    state.td3.critic, states)
        return population.at[half:].set(
            qfilter.select_best(candidates, scores, config.num_elite_filtered))

    return jax.lax.cond(state.total_steps >= config.q_filter_start, filtered,
                        lambda population: population, population)


def _choose(pred: jax.Array, on_true, on_false):
    """`on_true` if the scalar `pred` holds, else `on_false` (pytrees of one structure)."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


def _td3_return(config: PGPSConfig, returns: jax.Array) -> jax.Array:
    """The TD3 actor's return: slot N−1 (PG→EA), the probe slot N, or NaN where it never plays."""
    if config.pg_guides_ea:
        return returns[config.pop_size - 1]
    if config.td3_probe:
        return returns[config.pop_size]
    return jnp.asarray(jnp.nan)


@chex.dataclass(frozen=True)
class Played:
    """What a generation's episodes leave for its learning phase (`play_generation` →
    `learn_generation`)."""
    population: jax.Array        # [N, P] the actors that played (CEM ranks them)
    episodes: EpisodeState       # [N'] their episodes, N' = N (+1 with the TD3 probe)
    transitions: replay.Transition  # [t_max, N'] what they met, row by loop step
    valid: jax.Array             # [t_max, N'] rows to store in the buffer
    limit: jax.Array             # [] int32 the episode limit T of this generation
    td3_turn: jax.Array          # [] bool, the TD3 actor played (every F generations)
    train_key: jax.Array         # PRNG key of the TD3 updates
    evaluation: dict             # the `eval/*` metrics of an evaluation that ended


def play_generation(config: PGPSConfig, env: Env,
                    state: TrainState) -> tuple[TrainState, Played]:
    """Algorithm 1 lines 6-18: the generation's actors and their episodes.

    Returns `state` with its test evaluation advanced (and its key), and the episodes for
    `learn_generation`. Pure; `generation_step` is the two phases in one function.
    """
    td3, unflatten = _parts(config, env)
    (sample_key, candidate_key, states_key, reset_key, train_key,
     next_key) = jax.random.split(state.key, 6)
    n = config.pop_size
    td3_turn = ((state.generation + 1) % config.td3_to_cem_period) == 0

    population = _population(config, td3, unflatten, state, sample_key, candidate_key,
                             states_key)
    td3_flat = flatten(state.td3.actor)
    if config.pg_guides_ea:
        population = jnp.where(td3_turn, population.at[n - 1].set(td3_flat), population)
    limit = episode_limit(state.total_steps, config)
    actors, limits = population, jnp.full((n,), limit)
    if config.td3_probe:
        actors = jnp.concatenate([population, td3_flat[None]])
        limits = jnp.append(limits, jnp.where(td3_turn, limit, 0))
    num_rollout = actors.shape[0]

    # test episodes: an evaluation that falls due begins now, or is queued behind the one
    # under way; with one queued, the rollout runs on until it has begun if another could
    # fall due before the next generation (this rollout adds at most sum(limits) env steps)
    running = state.evaluation
    eval_due = state.total_steps >= state.next_eval
    begin_now, queue_now = eval_due & ~running.active, eval_due & running.active
    snapshot = _evaluated_actors(state)
    fresh = _test_episodes(config, env, state.eval_key, config.eval_steps)
    ongoing = running.replace(
        episodes=_choose(begin_now, fresh, running.episodes),
        actors=jnp.where(begin_now, snapshot, running.actors),
        step=jnp.where(begin_now, state.total_steps, running.step),
        active=running.active | begin_now,
        queued_actors=jnp.where(queue_now, snapshot, running.queued_actors),
        queued_step=jnp.where(queue_now, state.total_steps, running.queued_step),
        queued=running.queued | queue_now)
    next_eval = jnp.where(eval_due,
                          (state.total_steps // config.eval_every + 1) * config.eval_every,
                          state.next_eval)

    population_episodes = begin_episodes(env, jax.random.split(reset_key, num_rollout), limits)
    join = functools.partial(jax.tree.map, lambda a, b: jnp.concatenate([a, b]))
    test_slots = jnp.arange(num_rollout + fresh.alive.shape[0]) >= num_rollout
    per_actor = config.eval_episodes
    relay = Relay(slots=test_slots, episodes=join(population_episodes, fresh),
                  params=join(actors, evaluation_actors(ongoing.queued_actors, per_actor)),
                  pending=ongoing.queued,
                  hurry=ongoing.queued & (state.total_steps + limits.sum() >= next_eval),
                  ended_returns=jnp.zeros(test_slots.shape))
    batch, transitions, valid, relay = play(
        env, _policy(td3, unflatten),
        join(actors, evaluation_actors(ongoing.actors, per_actor)),
        join(population_episodes, ongoing.episodes), max(config.t_max, config.eval_steps),
        drive=~test_slots, relay=relay)
    eval_episodes = jax.tree.map(lambda x: x[num_rollout:], batch)
    # the evaluation under way when the rollout began has ended: at the hand-over, or by now
    handed_over = ongoing.queued & ~relay.pending
    eval_done = ongoing.active & (handed_over | ~jnp.any(eval_episodes.alive))
    eval_returns = jnp.where(handed_over, relay.ended_returns[num_rollout:],
                             eval_episodes.returns)
    after = _choose(handed_over, _begin_queued(ongoing, eval_episodes),
                    ongoing.replace(episodes=eval_episodes, active=ongoing.active & ~eval_done))
    state = state.replace(next_eval=next_eval, key=next_key, evaluation=after)
    return state, Played(population=population,
                         episodes=jax.tree.map(lambda x: x[:num_rollout], batch),
                         transitions=jax.tree.map(lambda x: x[:config.t_max, :num_rollout],
                                                  transitions),
                         valid=valid[:config.t_max, :num_rollout], limit=limit,
                         td3_turn=td3_turn, train_key=train_key,
                         evaluation=_evaluation_report(ongoing, eval_done, eval_returns))


def learn_generation(config: PGPSConfig, env: Env, state: TrainState,
                     played: Played) -> tuple[TrainState, dict]:
    """Algorithm 1 lines 19-37: the buffer takes the episodes' transitions, CEM ranks the
    population, TD3 trains (with L^A toward the elite if its actor fell behind). Returns the
    next state and the generation's metrics."""
    td3, unflatten = _parts(config, env)
    n = config.pop_size
    episodes, td3_turn = played.episodes, played.td3_turn
    buffer = replay.add(state.buffer, played.transitions, played.valid)
    interaction_steps = episodes.lengths.sum()

    returns = episodes.returns[:n]
    new_cem = cem.tell(state.cem, played.population, returns, top_k=config.top_k,
                       sigma_limit=config.sigma_limit, sigma_decay=config.sigma_decay,
                       divide_by_k=config.cem_divide_by_k)
    td3_in_episodes = config.pg_guides_ea or config.td3_probe
    td3_return = _td3_return(config, episodes.returns)
    if config.ea_guides_pg:
        guided = td3_turn & fell_behind(td3_return, returns, config.fell_behind_rule)
    else:
        guided = jnp.zeros((), bool)

    num_rollout = episodes.lengths.shape[0]
    num_update = interaction_steps // config.update_blocks
    max_update = num_rollout * config.t_max // config.update_blocks
    elite = unflatten(new_cem.elite)
    td3_state = state.td3
    if config.target_actor_from_elite:
        td3_state = td3_state.replace(actor_target=elite)
    new_td3, beta, losses = td3.train(td3_state, buffer, played.train_key, num_update,
                                      max_update, elite, guided, state.beta)
    generation = state.generation + 1
    new_state = state.replace(cem=new_cem, td3=new_td3, buffer=buffer, beta=beta,
                              generation=generation,
                              total_steps=state.total_steps + interaction_steps)
    metrics = {
        "gen/generation": generation,
        "gen/total_steps": new_state.total_steps,
        "gen/episode_limit": played.limit,
        "gen/interaction_steps": interaction_steps,
        "gen/q_filter_active": (state.total_steps >= config.q_filter_start) & config.q_filter,
        "pop/return_mean": jnp.mean(returns),
        "pop/return_std": jnp.std(returns),
        "pop/unstable_episodes": episodes.unstable.sum(),
        "cem/elite_return": jnp.max(returns),
        "cem/var_mean": jnp.mean(new_cem.var),
        "cem/damping": new_cem.damping,
        "td3/in_population": td3_turn & td3_in_episodes,
        "td3/return": jnp.where(td3_turn, td3_return, jnp.nan),
        "td3/fell_behind": guided,
        "td3/beta": beta,
        **{f"pop/return_{i}": returns[i] for i in range(n)},
        **losses,
        **played.evaluation,
    }
    return new_state, metrics


def generation_step(config: PGPSConfig, env: Env,
                    state: TrainState) -> tuple[TrainState, dict]:
    """One generation of Algorithm 1: `play_generation`, then `learn_generation`. Pure; bind
    config/env with `make_generation_step`."""
    return learn_generation(config, env, *play_generation(config, env, state))


EVALUATED = EVALUATED_ACTORS


def _test_episodes(config: PGPSConfig, env: Env, key: jax.Array, steps: int) -> EpisodeState:
    """Fresh test episodes [A·E] of `steps` steps (0: idle) from the E start states of `key`,
    the same for every actor, in EVALUATED order."""
    keys = evaluation_keys(key, len(EVALUATED), config.eval_episodes)
    return begin_episodes(env, keys, jnp.full((keys.shape[0],), steps))


def _begin_queued(evaluation: EvaluationState, episodes: EpisodeState) -> EvaluationState:
    """The queued evaluation under way in `episodes` [A·E], nothing queued behind it."""
    return evaluation.replace(episodes=episodes, actors=evaluation.queued_actors,
                              step=evaluation.queued_step, active=jnp.asarray(True),
                              queued=jnp.asarray(False))


def finish_evaluation(config: PGPSConfig, env: Env,
                      state: TrainState) -> tuple[TrainState, dict]:
    """Plays the evaluation under way to its end (for a run's last generation, whose test
    episodes no later generation will advance), then begins the queued one, if any. Returns
    the state and the `eval/*` metrics that generation_step reports; `eval/done` is False
    when no evaluation was under way. Call it until `state.evaluation.active` is False."""
    td3, unflatten = _parts(config, env)
    ongoing = state.evaluation
    episodes, _, _, _ = play(env, _policy(td3, unflatten),
                             evaluation_actors(ongoing.actors, config.eval_episodes),
                             ongoing.episodes, config.eval_steps, record=False)
    queued = _begin_queued(ongoing, _test_episodes(config, env, state.eval_key,
                                                   config.eval_steps))
    idle = ongoing.replace(episodes=episodes, active=jnp.asarray(False))
    evaluation = _choose(ongoing.queued, queued, idle)
    return (state.replace(evaluation=evaluation),
            _evaluation_report(ongoing, ongoing.active, episodes.returns))


def _evaluation_report(evaluation: EvaluationState, done: jax.Array,
                       returns: jax.Array) -> dict:
    """`eval/done`, `eval/step` (when the evaluation fell due) and the `evaluation_metrics` of
    its test returns, NaN unless `done`."""
    metrics = {k: jnp.where(done, v, jnp.nan) for k, v in evaluation_metrics(returns).items()}
    return {"eval/done": done, "eval/step": evaluation.step, **metrics}


def evaluation_keys(key: jax.Array, num_actors: int, episodes: int) -> jax.Array:
    """Reset keys [A·E] giving each of A actors the same E start states of `key`."""
    return jnp.tile(jax.random.split(key, episodes), (num_actors, 1))


def evaluation_actors(actors: jax.Array, episodes: int) -> jax.Array:
    """Actors [A, P] repeated to [A·E, P]: one row per test episode, E per actor."""
    return jnp.repeat(actors, episodes, axis=0)


def evaluation_batch(actors: jax.Array, key: jax.Array,
                     episodes: int) -> tuple[jax.Array, jax.Array]:
    """Actors [A, P] repeated to [A·E, P], and reset keys giving every actor the same E starts."""
    return (evaluation_actors(actors, episodes),
            evaluation_keys(key, actors.shape[0], episodes))


def _evaluated_actors(state: TrainState) -> jax.Array:
    return jnp.stack([state.cem.mean, flatten(state.td3.actor), state.cem.elite])


def evaluation_metrics(returns: jax.Array) -> dict:
    """Per-policy test returns [E] ("eval/mu_returns", ...) and their mean and std."""
    metrics = {}
    for name, policy_returns in zip(EVALUATED, returns.reshape(len(EVALUATED), -1)):
        metrics[f"eval/{name}_returns"] = policy_returns
        metrics[f"eval/{name}_mean"] = jnp.mean(policy_returns)
        metrics[f"eval/{name}_std"] = jnp.std(policy_returns)
    return metrics


def evaluate(config: PGPSConfig, env: Env, state: TrainState,
             key: jax.Array | None = None) -> dict:
    """Deterministic test episodes (Section 5.1) of μ, the TD3 actor and the elite, now.

    Each plays `eval_episodes` episodes of `eval_steps` steps, all in one batch, from the
    start states of `key` — by default `state.eval_key`, giving the same episodes that
    generation_step runs when an evaluation is due. Use it for a final or standalone test.
    """
    td3, unflatten = _parts(config, env)
    actors, keys = evaluation_batch(_evaluated_actors(state),
                                    state.eval_key if key is None else key, config.eval_episodes)
    episodes = run_episodes(env, _policy(td3, unflatten), actors, keys,
                            jnp.full((actors.shape[0],), config.eval_steps), config.eval_steps,
                            record=False)
    return evaluation_metrics(episodes.returns)


@functools.lru_cache(maxsize=None)
def make_init(config: PGPSConfig, env: Env) -> Callable[..., TrainState]:
    """Jitted `init` bound to `config` and `env`: (key, eval_key=None) -> TrainState (cached)."""
    return jax.jit(functools.partial(init, config, env))


@functools.lru_cache(maxsize=None)
def make_generation_step(config: PGPSConfig, env: Env,
                         donate: bool = True) -> Callable[[TrainState], tuple[TrainState, dict]]:
    """Jitted `generation_step` bound to `config` and `env` (cached per pair); the state is
    donated by default, so the buffer is updated in place (do not reuse the state passed in)."""
    return jax.jit(functools.partial(generation_step, config, env),
                   donate_argnums=(0,) if donate else ())


@functools.lru_cache(maxsize=None)
def make_generation_phases(config: PGPSConfig, env: Env) -> tuple[Callable, Callable]:
    """`play_generation` and `learn_generation` jitted apart (cached; each donates the state):
    `learn(*play(state))` is one generation, as `make_generation_step` computes it. Compiled
    side by side, the two programs are ready sooner than the one program of
    `generation_step`, and calling two programs per generation costs nothing measurable."""
    return (jax.jit(functools.partial(play_generation, config, env), donate_argnums=(0,)),
            jax.jit(functools.partial(learn_generation, config, env), donate_argnums=(0,)))


@functools.lru_cache(maxsize=None)
def make_finish_evaluation(config: PGPSConfig,
                           env: Env) -> Callable[[TrainState], tuple[TrainState, dict]]:
    """Jitted `finish_evaluation` bound to `config` and `env` (cached; state donated)."""
    return jax.jit(functools.partial(finish_evaluation, config, env), donate_argnums=(0,))


@functools.lru_cache(maxsize=None)
def make_evaluate(config: PGPSConfig, env: Env) -> Callable[..., dict]:
    """Jitted `evaluate` bound to `config` and `env`: (state, key=None) -> metrics (cached)."""
    return jax.jit(functools.partial(evaluate, config, env))

"""Test evaluation (Section 5.1): deterministic episodes of μ, the TD3 actor and the elite.

Every actor plays E episodes from the same E start states (drawn from a fixed key, the
paper's seed + 100), with the mean return reported per actor.

`evaluate` plays an evaluation now, in one batch. During training the evaluation rides along
with the population instead: `begin_if_due` starts one when `every` env steps have passed and
none is under way, its episodes fill extra slots of the population's rollout that do not drive
its loop (so they add no sequential env steps), and `advanced` takes them back after each
rollout and reports the evaluation once all of its episodes have ended. So that no
evaluation is skipped, one under way whose successor could fall due before the next rollout
(`must_end_now`) drives the loop of this rollout to its end; an evaluation that falls due
while another is still under way all the same begins when that one has ended. Multiples of
`every` that one generation crosses together give one evaluation: the actors it would test
are the same for each.
"""

from typing import Callable

import chex
import jax
import jax.numpy as jnp

from pgps_jax.agent.config import EvaluationConfig
from pgps_jax.agent.metrics import returns_key
from pgps_jax.envs import Env, env_batches
from pgps_jax.agent.rollout import EpisodeState, begin_episodes, run_episodes


@chex.dataclass(frozen=True)
class EvaluationState:
    """The evaluation under way, carried from generation to generation."""
    episodes: EpisodeState   # [A·E] its test episodes, E per actor, in the actors' order
    actors: jax.Array        # [A, P] the actors as they were when it began
    step: jax.Array          # [] int32 env steps when it began
    active: jax.Array        # [] bool, begun and not yet reported
    next_due: jax.Array      # [] int32 env steps at which the next one falls due
    key: jax.Array           # PRNG key of the start states, the same for every evaluation


@chex.dataclass(frozen=True)
class Report:
    """An evaluation as a generation reports it; read `returns` only when `done`."""
    done: jax.Array          # [] bool, an evaluation ended in this generation
    step: jax.Array          # [] int32 env steps when it began
    returns: jax.Array       # [A, E] its test returns


def start_keys(key: jax.Array, num_actors: int, episodes: int) -> jax.Array:
    """Reset keys [A·E] giving each of A actors the same E start states of `key` (raw or
    typed keys)."""
    return jnp.concatenate([jax.random.split(key, episodes)] * num_actors)


def repeat_actors(actors: jax.Array, episodes: int) -> jax.Array:
    """Actors [A, P] repeated to [A·E, P]: one row per test episode, E per actor."""
    return jnp.repeat(actors, episodes, axis=0)


def evaluate(config: EvaluationConfig, env: Env, policy: Callable, actors: jax.Array,
             key: jax.Array) -> jax.Array:
    """Test returns [A, E] of `actors` [A, P], played now in one batch."""
    num_actors = actors.shape[0]
    episodes = run_episodes(env, policy, repeat_actors(actors, config.episodes),
                            start_keys(key, num_actors, config.episodes),
                            jnp.full((num_actors * config.episodes,), config.steps),
                            config.steps, record=False)
    return episodes.returns.reshape(num_actors, config.episodes)


def _episodes(config: EvaluationConfig, env: Env, key: jax.Array, num_actors: int,
              steps: int) -> EpisodeState:
    keys = start_keys(key, num_actors, config.episodes)
    return begin_episodes(env, keys, jnp.full((keys.shape[0],), steps))


def idle(config: EvaluationConfig, env: Env, actors: jax.Array,
         key: jax.Array) -> EvaluationState:
    """No evaluation under way; the first falls due at once. `actors` [A, P] gives the
    shapes."""
    zero = jnp.zeros((), jnp.int32)
    return EvaluationState(episodes=_episodes(config, env, key, actors.shape[0], steps=0),
                           actors=actors,
                           step=zero, active=jnp.asarray(False), next_due=zero, key=key)


def begin_if_due(config: EvaluationConfig, env: Env, evaluation: EvaluationState,
                 actors: jax.Array, total_steps: jax.Array) -> EvaluationState:
    """Begins testing `actors` [A, P] if an evaluation is due (`every` env steps since the
    last fell due) and none is under way; the next then falls due at the next multiple."""
    begin = (total_steps >= evaluation.next_due) & ~evaluation.active
    fresh = evaluation.replace(
        episodes=_episodes(config, env, evaluation.key, actors.shape[0], config.steps),
        actors=actors,
        step=total_steps.astype(jnp.int32), active=jnp.asarray(True),
        next_due=((total_steps // config.every + 1) * config.every).astype(jnp.int32))
    return env_batches.select(begin, fresh, evaluation)


def must_end_now(evaluation: EvaluationState, steps_after: jax.Array) -> jax.Array:
    """Whether the evaluation under way must end in this rollout: the env steps may reach
    `steps_after` by its end, when the next evaluation falls due (it would otherwise wait,
    and begin from a later state than the one it fell due at)."""
    return evaluation.active & (steps_after >= evaluation.next_due)


def advanced(evaluation: EvaluationState,
             episodes: EpisodeState) -> tuple[EvaluationState, Report]:
    """The evaluation after a rollout moved its `episodes`, and its report: done when it was
    under way and all of its episodes have now ended."""
    done = evaluation.active & ~jnp.any(episodes.alive)
    report = Report(done=done, step=evaluation.step,
                    returns=episodes.returns.reshape(evaluation.actors.shape[0], -1))
    return evaluation.replace(episodes=episodes, active=evaluation.active & ~done), report


def metrics(returns: jax.Array, actors: tuple[str, ...]) -> dict:
    """Per-actor test returns [E] (`metrics.returns_key`) and their mean and std
    (`metrics.evaluation_metrics`), from `returns` [A, E] of the named `actors`."""
    out = {}
    for name, actor_returns in zip(actors, returns, strict=True):
        out[returns_key(name)] = actor_returns
        out[f"eval/{name}_mean"] = jnp.mean(actor_returns)
        out[f"eval/{name}_std"] = jnp.std(actor_returns)
    return out

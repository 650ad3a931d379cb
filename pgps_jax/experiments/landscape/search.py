"""The linear tanh policy, its episodes, and its CEM training (step 1)."""

import dataclasses
import functools
import math
import pathlib
from typing import Callable, Union

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax.agent import cem
from pgps_jax.envs import Env
from pgps_jax.cli.errors import UsageError
from pgps_jax.agent.rollout import Episodes, run_episodes
from pgps_jax.experiments.landscape.config import TrainConfig


def linear_policy(theta: jax.Array, obs: jax.Array) -> jax.Array:
    """a = tanh(s·W), W = theta [obs_dim, action_dim], no bias: Appendix A's linear actor."""
    return jnp.tanh(obs @ theta)


def evaluate(env: Env, thetas: jax.Array, reset_keys: jax.Array, steps: int,
             gamma: float) -> Episodes:
    """One deterministic episode of `steps` steps per (theta, key): thetas [B, obs, act]."""
    batch = thetas.shape[0]
    chex.assert_shape(thetas, (batch, env.observation_size, env.action_size))
    chex.assert_axis_dimension(reset_keys, 0, batch)
    return run_episodes(env, linear_policy, thetas, reset_keys,
                        jnp.full((batch,), steps, jnp.int32), steps, record=False, gamma=gamma)


def point_seed_pairs(thetas: jax.Array, keys: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Every theta [A, ...] with every key [S, ...], as flat batches [A·S, ...] (theta-major)."""
    num_a, num_s = thetas.shape[0], keys.shape[0]
    batch_thetas = jnp.repeat(thetas, num_s, axis=0)
    batch_keys = jnp.broadcast_to(keys[None], (num_a,) + keys.shape)
    return batch_thetas, batch_keys.reshape((num_a * num_s,) + keys.shape[1:])


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """What `train_linear_policy` found (host values)."""

    theta: np.ndarray         # [obs, act] parameters to sweep around
    mean_return: float        # their average return over `eval_episodes` episodes
    generations: int          # generations run
    reached: bool             # whether mean_return exceeded the threshold


def cem_generation(env: Env, config: TrainConfig, state: cem.CEMState,
                   key: jax.Array) -> tuple[cem.CEMState, jax.Array, jax.Array, dict]:
    """One CEM generation on the flat W; fitness = episode return, MAXIMISED.

    The population is the current elite plus pop_size − 1 samples of N(μ, Σ) (Algorithm 1,
    line 8). One batch of episodes scores the samples (one episode each) and the current mean
    μ and elite (`eval_episodes` each; the elite's fitness is that average), then `cem.tell`
    updates the distribution. Returns (state', candidates [2, P] = (μ, elite) before the
    update, their average returns [2], metrics).
    """
    sample_key, episode_key = jax.random.split(key)
    shape = (env.observation_size, env.action_size)
    reps = config.eval_episodes
    samples = cem.ask(sample_key, state, config.pop_size - 1)               # [N-1, P]
    candidates = jnp.stack([state.mean, state.elite])                        # [2, P]
    thetas = jnp.concatenate([jnp.repeat(candidates, reps, axis=0), samples])
    returns = evaluate(env, thetas.reshape((-1,) + shape),
                       jax.random.split(episode_key, thetas.shape[0]), config.steps,
                       1.0).returns
    scores = returns[:2 * reps].reshape(2, reps).mean(axis=1)                # [2] μ, elite
    population = jnp.concatenate([state.elite[None], samples])              # [N, P]
    fitness = jnp.concatenate([scores[1:], returns[2 * reps:]])              # [N]
    state = cem.tell(state, population, fitness, top_k=config.top_k,
                     sigma_limit=config.sigma_limit, sigma_decay=config.sigma_decay,
                     divide_by_k=config.divide_by_k)
    metrics = {"cem/pop_best": fitness.max(), "cem/pop_mean": fitness.mean(),
               "cem/sigma_mean": jnp.sqrt(state.var).mean(),
               "eval/mean_return": scores[0], "eval/elite_return": scores[1]}
    return state, candidates, scores, metrics


def train_linear_policy(env: Env, config: TrainConfig, key: jax.Array,
                        log: Callable[[str], None] = print) -> TrainResult:
    """CEM from μ = 0 (W = 0) until a candidate's average return exceeds `config.threshold`.

    Host loop over jitted generations (logging stays on the host). After `max_generations`
    without success it gives up, says so through `log`, and returns the best candidate seen.
    """
    shape = (env.observation_size, env.action_size)
    state = cem.init(jnp.zeros(math.prod(shape), jnp.float32), config.sigma_init)
    step = jax.jit(functools.partial(cem_generation, env, config))
    best_theta, best_return = np.zeros(shape, np.float32), -np.inf
    generation = 0
    for generation in range(1, config.max_generations + 1):
        state, candidates, scores, metrics = step(state, jax.random.fold_in(key, generation))
        scores = np.asarray(scores)
        i = int(np.argmax(scores))
        if scores[i] > best_return:
            best_return = float(scores[i])
            best_theta = np.asarray(candidates[i]).reshape(shape)
        log(f"cem generation {generation:4d}: " + " ".join(
            f"{k}={float(v):9.2f}" for k, v in metrics.items()))
        if best_return > config.threshold:
            return TrainResult(theta=best_theta, mean_return=best_return,
                               generations=generation, reached=True)
    log(f"CEM gave up: no candidate exceeded threshold={config.threshold} within "
        f"max_generations={config.max_generations} (best average return {best_return:.2f}); "
        "sweeping around the best parameters found instead.")
    return TrainResult(theta=best_theta, mean_return=best_return, generations=generation,
                       reached=False)


def save_theta(path: pathlib.Path, result: TrainResult, env_name: str) -> None:
    """(host) Writes W and how it was found to an npz that `load_theta` reads back."""
    np.savez(path, theta=result.theta, mean_return=result.mean_return,
             generations=result.generations, reached=result.reached, env=env_name)


def load_theta(path: Union[str, pathlib.Path], shape: tuple) -> np.ndarray:
    """(host) W [obs, act] from an npz written by `save_theta`; checks it fits the task."""
    with np.load(path) as data:
        if "theta" not in data:
            raise UsageError(f"params_file={str(path)!r} has no 'theta' array "
                             f"(found {sorted(data.files)}); write it with save_theta")
        theta = np.asarray(data["theta"], np.float32)
    if theta.shape != tuple(shape):
        raise UsageError(f"params_file={str(path)!r} holds W of shape {theta.shape}, but this "
                         f"task's linear policy needs [obs, act] = {tuple(shape)}")
    return theta

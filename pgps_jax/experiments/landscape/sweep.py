"""One-parameter sweeps of a trained linear policy, and their analysis (step 2)."""

import functools
from typing import Callable

import chex
import jax
import numpy as np

from pgps_jax.envs import Env
from pgps_jax.experiments.landscape.config import SweepConfig
from pgps_jax.experiments.landscape.search import point_seed_pairs, evaluate


@chex.dataclass(frozen=True)
class Sweep:
    """Episodes of one parameter's sweep: every value × every seed."""

    values: jax.Array       # [V] values taken by the swept entry
    discounted: jax.Array   # [V, S] Σ_t γ^t r_t of each point and seed
    returns: jax.Array      # [V, S] Σ_t r_t of each point and seed
    unstable: jax.Array     # [V, S] bool, the episode ended on non-finite physics


def sweep_thetas(theta: jax.Array, index: jax.Array, values: jax.Array) -> jax.Array:
    """[V, obs, act] copies of theta [obs, act] whose flat entry `index` takes each value."""
    flat = theta.reshape(-1)
    return jax.vmap(lambda v: flat.at[index].set(v).reshape(theta.shape))(values)


def sweep_parameter(env: Env, theta: jax.Array, index: jax.Array, values: jax.Array,
                    reset_keys: jax.Array, *, steps: int, gamma: float) -> Sweep:
    """Evaluate theta with entry `index` set to each of `values` [V] on each key [S].

    All V·S episodes run as one vmapped batch; `index` may be traced, so one compiled
    function serves every entry of W.
    """
    num_v, num_s = values.shape[0], reset_keys.shape[0]
    thetas, keys = point_seed_pairs(sweep_thetas(theta, index, values), reset_keys)
    episodes = evaluate(env, thetas, keys, steps, gamma)
    return Sweep(values=values, discounted=episodes.discounted.reshape(num_v, num_s),
                 returns=episodes.returns.reshape(num_v, num_s),
                 unstable=episodes.unstable.reshape(num_v, num_s))


def make_sweep(env: Env, steps: int, gamma: float) -> Callable[..., Sweep]:
    """Jitted `sweep_parameter(theta, index, values, reset_keys)` with the env bound."""
    return jax.jit(functools.partial(sweep_parameter, env, steps=steps, gamma=gamma))


def sweep_values(center: float, config: SweepConfig) -> np.ndarray:
    """[points] values of one entry: center + linspace(low, high), or linspace if absolute."""
    offset = center if config.relative else 0.0
    return (offset + np.linspace(config.low, config.high, config.points)).astype(np.float32)


def analyse_curve(values: np.ndarray, curve: np.ndarray, flat_tol: float = 0.2,
                  flat_atol: float = 1e-6) -> dict:
    """Flatness and steps of a curve J(θ) sampled on an increasing grid `values`.

    Finite differences over the grid, g_k = (J_{k+1} − J_k)/(θ_{k+1} − θ_k). A segment is
    "near zero gradient" when |g_k| ≤ flat_tol · (max J − min J)/(θ_max − θ_min): its slope is
    under `flat_tol` times that of a straight line rising through the curve's whole range
    over the whole sweep (a linear curve has no flat segment for flat_tol < 1, a step
    function is flat everywhere but at the step). A curve whose range is ≤ `flat_atol` is
    flat everywhere.

    Returns flat_fraction (the share of the swept width covered by flat segments), max_jump
    (largest |J_{k+1} − J_k|), max_jump_at (midpoint of that segment), max_jump_relative
    (max_jump over the curve's range, 0 for a flat curve) and range.
    """
    values = np.asarray(values, np.float64)
    curve = np.asarray(curve, np.float64)
    dx, dy = np.diff(values), np.diff(curve)
    if np.any(dx <= 0):
        raise ValueError("analyse_curve needs strictly increasing values")
    span = float(curve.max() - curve.min())
    if span <= flat_atol:
        flat = np.ones_like(dx, bool)
    else:
        flat = np.abs(dy / dx) <= flat_tol * span / (values[-1] - values[0])
    k = int(np.argmax(np.abs(dy)))
    return {"flat_fraction": float(dx[flat].sum() / dx.sum()),
            "max_jump": float(np.abs(dy[k])),
            "max_jump_at": float(0.5 * (values[k] + values[k + 1])),
            "max_jump_relative": float(np.abs(dy[k]) / span) if span > flat_atol else 0.0,
            "range": span}

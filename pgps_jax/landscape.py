"""The objective landscape of a linear tanh policy, one parameter at a time (Appendix A).

Appendix A of the paper (Figures 1 and 7) explains why gradient methods struggle on swimmer:
train a linear actor a = tanh(s·W), W ∈ R^{obs × act} and no bias, with the CEM until its
return exceeds 200; then move one entry of W over a range while the others stay fixed and
evaluate each point on 30 seeds, recording

    J(s_0)  ≈ 1/30 Σ_n Σ_{t=0}^{999} γ^t r_t   (average discounted return, γ = 0.99)
    Return  ≈ 1/30 Σ_n Σ_{t=0}^{999} r_t       (average undiscounted return).

The curves show wide flat regions (∇_θ J ≈ 0) and steep, step-like jumps.

Pieces (pure functions; host-side I/O is kept in the functions marked "host"):
- `linear_policy`, `evaluate`: the actor and a batch of its episodes (`rollout.run_episodes`).
- `cem_generation` / `train_linear_policy`: the project's CEM (`cem.py`) on the flat W; one
  jitted generation, a host loop that stops at the threshold or gives up after
  `max_generations` and keeps the best parameters found.
- `sweep_parameter`: every point × seed of one parameter in ONE vmapped batch of episodes.
  The entry index is traced, so all parameters share one compiled function. Every point uses
  the same 30 reset keys (common random numbers), so differences between neighbouring points
  come from the parameter, not from the seeds.
- `analyse_curve`: flat fraction and largest jump of a curve (see its docstring).
- `run` (host): train or load, sweep, write CSVs, `theta.npz`, `landscape.png`, analysis.

Command line (Hydra, config `configs/landscape.yaml`):

    python -m pgps_jax.landscape env=swimmer [threshold=200] [params_file=theta.npz]
        [sweep.params='[0,5,[3,1]]'] [sweep.points=41] [sweep.seeds=30] [steps=1000]
"""

import csv
import dataclasses
import functools
import logging
import math
import pathlib
import sys
import time
import typing
from typing import Callable, Optional, Sequence, Union

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax import cem
from pgps_jax.envs import Env
from pgps_jax.errors import EXIT_OK, UsageError, report
from pgps_jax.rollout import Episodes, run_episodes
from pgps_jax.run_config import coerce, parse_overrides

CSV_COLUMNS = ("value", "discounted_mean", "discounted_std", "return_mean", "return_std",
               "unstable_fraction")
"""Columns of each parameter's CSV; one row per swept value (means/stds over the seeds)."""

ANALYSIS_COLUMNS = ("parameter", "row", "col", "trained_value", "flat_fraction",
                    "max_jump_discounted", "max_jump_at", "max_jump_relative",
                    "max_jump_return", "discounted_range", "return_range")
"""Columns of `analysis.csv`, one row per panel (see `analyse_curve`)."""


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """CEM search for a linear policy whose return exceeds `threshold` (Appendix A, step 1)."""

    threshold: float = 200.0
    """Stop once a candidate's average return over `eval_episodes` exceeds this."""
    pop_size: int = 32
    """Actors per generation (the first is last generation's elite)."""
    top_k: int = 16
    """Actors that update the search distribution."""
    sigma_init: float = 0.1
    """Initial variance (and additive damping) of the diagonal CEM, around W = 0."""
    sigma_limit: float = 1e-3
    """Value the additive damping decays toward."""
    sigma_decay: float = 0.05
    """Damping ← (1 − τ)·damping + τ·sigma_limit each generation."""
    divide_by_k: bool = False
    """Divide the weighted variance by K (as the PGPS CEM does); off gives a wider search."""
    max_generations: int = 200
    """Give up after this many generations and sweep around the best parameters found."""
    eval_episodes: int = 5
    """Episodes on which the CEM mean and elite are scored against the threshold."""
    steps: int = 1000
    """Episode length of training episodes."""

    def __post_init__(self):
        _require(self.pop_size >= 2, "cem.pop_size", self.pop_size, "an integer >= 2")
        _require(1 <= self.top_k <= self.pop_size, "cem.top_k", self.top_k,
                 f"in [1, pop_size={self.pop_size}]")
        for name in ("sigma_init", "sigma_limit"):
            _require(getattr(self, name) > 0, f"cem.{name}", getattr(self, name), "> 0")
        _require(0 < self.sigma_decay <= 1, "cem.sigma_decay", self.sigma_decay, "in (0, 1]")
        _require(self.max_generations >= 0, "cem.max_generations", self.max_generations,
                 "a non-negative integer")
        _require(self.eval_episodes >= 1, "cem.eval_episodes", self.eval_episodes,
                 "a positive integer")
        _require(self.steps >= 1, "steps", self.steps, "a positive integer")


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """Which parameters to sweep, over which values, on how many seeds (Appendix A, step 2)."""

    params: Optional[tuple] = None
    """Entries of W: flat indices (row-major) or (row, col) pairs; None → `num_params` spread."""
    num_params: int = 6
    """How many entries to pick, evenly spread over W, when `params` is None."""
    low: float = -2.0
    """Start of the sweep (an offset from the trained value when `relative`)."""
    high: float = 2.0
    """End of the sweep (an offset from the trained value when `relative`)."""
    relative: bool = True
    """Sweep θ_ij + linspace(low, high) (True) or linspace(low, high) itself (False)."""
    points: int = 81
    """Values per parameter."""
    seeds: int = 30
    """Episodes per value (the same reset keys at every value)."""
    steps: int = 1000
    """Episode length (the paper: 1000)."""
    gamma: float = 0.99
    """Discount of J(s_0) (the paper: 0.99)."""
    flat_tol: float = 0.2
    """A finite-difference slope is near zero when |ΔJ/Δθ| ≤ flat_tol · range(J)/range(θ)."""
    flat_atol: float = 1e-6
    """A curve whose whole range is at most this is flat everywhere."""

    def __post_init__(self):
        _require(self.num_params >= 1, "sweep.num_params", self.num_params, "a positive integer")
        _require(self.low < self.high, "sweep.low", self.low, f"< sweep.high={self.high}")
        _require(self.points >= 2, "sweep.points", self.points, "an integer >= 2")
        _require(self.seeds >= 1, "sweep.seeds", self.seeds, "a positive integer")
        _require(self.steps >= 1, "steps", self.steps, "a positive integer")
        _require(0 <= self.gamma <= 1, "gamma", self.gamma, "in [0, 1]")
        _require(self.flat_tol >= 0, "sweep.flat_tol", self.flat_tol, ">= 0")
        _require(self.flat_atol >= 0, "sweep.flat_atol", self.flat_atol, ">= 0")


def _require(ok: bool, field: str, value, valid: str) -> None:
    if not ok:
        raise UsageError(f"landscape config {field}={value!r} is invalid: must be {valid}")


def resolve_params(spec: Optional[Sequence[Union[int, Sequence[int]]]], shape: tuple,
                   num_params: int) -> list[int]:
    """Flat (row-major) indices of the entries of W [obs, act] to sweep.

    `spec` items are flat indices or (row, col) pairs; None picks `num_params` indices evenly
    spread over the flattened matrix (first and last included). Raises UsageError if an index
    lies outside W.
    """
    rows, cols = shape
    size = rows * cols
    if spec is None:
        count = min(num_params, size)
        return sorted({int(round(i)) for i in np.linspace(0, size - 1, count)})
    indices = []
    for item in spec:
        if isinstance(item, (int, np.integer)):
            flat = int(item)
            _require(0 <= flat < size, "sweep.params", item,
                     f"a flat index in [0, {size}) of W [{rows}, {cols}]")
        else:
            row, col = (int(x) for x in item)
            _require(0 <= row < rows and 0 <= col < cols, "sweep.params", list(item),
                     f"a [row, col] pair inside W [{rows}, {cols}]")
            flat = row * cols + col
        indices.append(flat)
    _require(len(indices) > 0, "sweep.params", spec, "non-empty (or null for the default)")
    return indices


# --------------------------------------------------------------------------------------------
# Policy and evaluation
# --------------------------------------------------------------------------------------------

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


def _pairs(thetas: jax.Array, keys: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Every theta [A, ...] with every key [S, ...], as flat batches [A·S, ...] (theta-major)."""
    num_a, num_s = thetas.shape[0], keys.shape[0]
    batch_thetas = jnp.repeat(thetas, num_s, axis=0)
    batch_keys = jnp.broadcast_to(keys[None], (num_a,) + keys.shape)
    return batch_thetas, batch_keys.reshape((num_a * num_s,) + keys.shape[1:])


# --------------------------------------------------------------------------------------------
# Step 1: CEM training of the linear policy
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# Step 2: one-parameter sweeps
# --------------------------------------------------------------------------------------------

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
    thetas, keys = _pairs(sweep_thetas(theta, index, values), reset_keys)
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


# --------------------------------------------------------------------------------------------
# Analysis
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# Output (host)
# --------------------------------------------------------------------------------------------

def param_label(index: int, shape: tuple) -> str:
    """'W[row,col]' for a flat index into W [obs, act]."""
    row, col = divmod(index, shape[1])
    return f"W[{row},{col}]"


def write_sweep_csv(path: pathlib.Path, sweep: Sweep) -> None:
    """(host) One row per value with `CSV_COLUMNS` (mean and std over the seeds)."""
    disc, ret = np.asarray(sweep.discounted), np.asarray(sweep.returns)
    unstable = np.asarray(sweep.unstable, np.float64)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        for i, value in enumerate(np.asarray(sweep.values)):
            writer.writerow([f"{value:.6g}", f"{disc[i].mean():.6g}", f"{disc[i].std():.6g}",
                             f"{ret[i].mean():.6g}", f"{ret[i].std():.6g}",
                             f"{unstable[i].mean():.6g}"])


def plot_landscape(path: pathlib.Path, sweeps: Sequence[Sweep], labels: Sequence[str],
                   trained: Sequence[float], title: str) -> None:
    """(host) One panel per parameter: discounted (left axis) and undiscounted return (right
    axis) means, shaded ± std over the seeds, trained value dashed (like Figure 7)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = min(3, len(sweeps))
    nrows = -(-len(sweeps) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.0 * nrows), squeeze=False)
    for ax, sweep, label, center in zip(axes.flat, sweeps, labels, trained):
        x = np.asarray(sweep.values)
        twin = ax.twinx()
        for axis, data, color, name in ((ax, sweep.discounted, "tab:blue", "discounted J(s0)"),
                                        (twin, sweep.returns, "tab:red", "return")):
            data = np.asarray(data)
            mean, std = data.mean(axis=1), data.std(axis=1)
            axis.plot(x, mean, color=color, lw=1.4, label=name)
            axis.fill_between(x, mean - std, mean + std, color=color, alpha=0.2, lw=0)
            axis.tick_params(axis="y", labelcolor=color, labelsize=7)
        ax.axvline(center, color="grey", ls="--", lw=0.8)
        ax.set_title(label, fontsize=9)
        ax.tick_params(axis="x", labelsize=7)
        ax.set_ylabel("discounted J(s0)", color="tab:blue", fontsize=8)
        twin.set_ylabel("return", color="tab:red", fontsize=8)
    for ax in list(axes.flat)[len(sweeps):]:
        ax.set_visible(False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def format_analysis(rows: Sequence[dict]) -> str:
    """(host) The end-of-run table: one line per panel."""
    lines = [f"{'parameter':>10} {'trained':>8} {'flat frac':>9} {'max jump J':>10} "
             f"{'at':>8} {'jump/range':>10} {'max jump R':>10}"]
    for r in rows:
        lines.append(f"{r['parameter']:>10} {r['trained_value']:8.3f} {r['flat_fraction']:9.2f} "
                     f"{r['max_jump_discounted']:10.3f} {r['max_jump_at']:8.3f} "
                     f"{r['max_jump_relative']:10.2f} {r['max_jump_return']:10.2f}")
    return "\n".join(lines)


def run(env: Env, env_name: str, train_config: TrainConfig, sweep_config: SweepConfig,
        out_dir: Union[str, pathlib.Path], key: jax.Array, params: Optional[Sequence] = None,
        params_file: Optional[str] = None, log: Callable[[str], None] = print) -> list[dict]:
    """(host) Appendix A end to end; returns the analysis rows (also in analysis.csv).

    Writes to `out_dir`: theta.npz (trained or loaded W), sweep_<row>_<col>.csv per parameter,
    landscape.png and analysis.csv.
    """
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    shape = (env.observation_size, env.action_size)
    indices = resolve_params(params, shape, sweep_config.num_params)
    train_key, sweep_key = jax.random.split(key)
    start = time.perf_counter()
    if params_file:
        theta = load_theta(params_file, shape)
        result = TrainResult(theta=theta, mean_return=float("nan"), generations=0, reached=False)
        log(f"loaded W {shape} from {params_file}")
    else:
        result = train_linear_policy(env, train_config, train_key, log)
        theta = result.theta
        log(f"CEM: average return {result.mean_return:.2f} after {result.generations} "
            f"generations ({time.perf_counter() - start:.1f} s)")
    save_theta(out / "theta.npz", result, env_name)

    sweep = make_sweep(env, sweep_config.steps, sweep_config.gamma)
    reset_keys = jax.random.split(sweep_key, sweep_config.seeds)
    sweeps, labels, rows = [], [], []
    for index in indices:
        tick = time.perf_counter()
        row, col = divmod(index, shape[1])
        center = float(theta.reshape(-1)[index])
        values = sweep_values(center, sweep_config)
        result_i = jax.device_get(sweep(jnp.asarray(theta), jnp.asarray(index, jnp.int32),
                                        jnp.asarray(values), reset_keys))
        write_sweep_csv(out / f"sweep_{row}_{col}.csv", result_i)
        disc = analyse_curve(values, result_i.discounted.mean(axis=1), sweep_config.flat_tol,
                             sweep_config.flat_atol)
        ret = analyse_curve(values, result_i.returns.mean(axis=1), sweep_config.flat_tol,
                            sweep_config.flat_atol)
        label = param_label(index, shape)
        rows.append({"parameter": label, "row": row, "col": col, "trained_value": center,
                     "flat_fraction": disc["flat_fraction"],
                     "max_jump_discounted": disc["max_jump"], "max_jump_at": disc["max_jump_at"],
                     "max_jump_relative": disc["max_jump_relative"],
                     "max_jump_return": ret["max_jump"], "discounted_range": disc["range"],
                     "return_range": ret["range"]})
        sweeps.append(result_i)
        labels.append(label)
        log(f"swept {label}: {values.size} points x {sweep_config.seeds} seeds in "
            f"{time.perf_counter() - tick:.1f} s")

    with open(out / "analysis.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=ANALYSIS_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    trained_note = ("loaded" if params_file else
                    f"CEM return {result.mean_return:.0f}" + ("" if result.reached else
                                                              ", threshold not reached"))
    plot_landscape(out / "landscape.png", sweeps, labels,
                   [float(theta.reshape(-1)[i]) for i in indices],
                   f"{env_name}: linear tanh policy ({trained_note}); mean ± std over "
                   f"{sweep_config.seeds} seeds, γ={sweep_config.gamma}, "
                   f"{sweep_config.steps} steps")
    log(f"analysis (discounted return J; flat = |dJ/dθ| ≤ {sweep_config.flat_tol} · "
        "range(J)/range(θ)):\n" + format_analysis(rows))
    log(f"wrote {out} ({time.perf_counter() - start:.1f} s in all)")
    return rows


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

CONFIG_DIR = pathlib.Path(__file__).resolve().parent.parent / "configs"
_SECTIONS = {"cem": TrainConfig, "sweep": SweepConfig}
_TOP = {"seed": int, "threshold": float, "params_file": str, "steps": int, "gamma": float,
        "output_dir": str}


def _fields(section: str) -> list[str]:
    return [f.name for f in dataclasses.fields(_SECTIONS[section])
            if f.name not in ("steps", "threshold")]


def _valid_settings_text() -> str:
    return ("valid settings: env=<task>, " + ", ".join(_TOP) + ", "
            + ", ".join(f"{s}.{f}" for s in _SECTIONS for f in _fields(s)))


def check_overrides(args: Sequence[str]) -> None:
    """Checks the command line before Hydra composes it: unknown keys and tasks."""
    from pgps_jax.envs import TASKS
    for o in parse_overrides(args):
        key = o.key_or_group
        if key.startswith("hydra"):
            continue
        if key == "env":
            if o.value() not in TASKS:
                raise UsageError(f"unknown env {o.value()!r}; choices: {', '.join(TASKS)}")
            continue
        section, _, field = key.partition(".")
        if key in _TOP or (section in _SECTIONS and field in _fields(section)):
            continue
        raise UsageError(f"unknown setting {key!r}; {_valid_settings_text()}")


def configs_from_dict(cfg: dict) -> tuple[TrainConfig, SweepConfig]:
    """Validated dataclasses from the `configs/landscape.yaml` layout (a plain dict); a
    UsageError names a value of the wrong type or out of range."""
    steps, gamma = coerce("steps", cfg["steps"], int), coerce("gamma", cfg["gamma"], float)
    threshold = coerce("threshold", cfg["threshold"], float)
    kwargs = {}
    for section, kind in _SECTIONS.items():
        hints = typing.get_type_hints(kind)
        given = cfg.get(section) or {}
        kwargs[section] = {k: v if k == "params" else coerce(f"{section}.{k}", v, hints[k])
                           for k, v in given.items() if k in _fields(section)}
    train = TrainConfig(threshold=threshold, steps=steps, **kwargs["cem"])
    sweep = SweepConfig(steps=steps, gamma=gamma,
                        **{k: v for k, v in kwargs["sweep"].items() if k != "params"})
    return train, sweep


def _main(cfg) -> None:
    """Hydra entry: `python -m pgps_jax.landscape env=swimmer`."""
    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf
    from pgps_jax.envs import make_env

    def body() -> int:
        plain = OmegaConf.to_container(cfg, resolve=True)
        train, sweep = configs_from_dict(plain)
        name = HydraConfig.get().runtime.choices["env"]
        out_dir = plain.get("output_dir") or HydraConfig.get().runtime.output_dir
        params_file = plain.get("params_file")
        if params_file:
            params_file = hydra.utils.to_absolute_path(params_file)
        run(make_env(name), name, train, sweep, out_dir,
            jax.random.PRNGKey(coerce("seed", plain["seed"], int)),
            params=plain.get("sweep", {}).get("params"), params_file=params_file,
            log=logging.getLogger(__name__).info)
        return EXIT_OK

    code = report(body)
    if code != EXIT_OK:
        sys.exit(code)


def main() -> None:
    """Checks the command line, then runs `_main` under Hydra (configs/landscape.yaml)."""
    import hydra
    code = report(lambda: check_overrides(sys.argv[1:]) or EXIT_OK)
    if code != EXIT_OK:
        sys.exit(code)
    hydra.main(config_path=str(CONFIG_DIR), config_name="landscape", version_base=None)(_main)()


if __name__ == "__main__":
    main()

"""Settings of the landscape experiment: the CEM search and the sweep."""

import dataclasses
from typing import Optional, Sequence, Union

import numpy as np

from pgps_jax.cli.errors import UsageError


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

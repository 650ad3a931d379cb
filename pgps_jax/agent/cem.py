"""Diagonal Cross-Entropy Method with rank weights, elitism and decaying additive noise.

Pure `init / ask / tell` on an explicit CEMState (Section 3, Figure 2b; the update follows
the authors' code, itself derived from CEM-RL):
    w_i ∝ log(1 + K) − log(i), i = 1..K (normalised)
    μ'   = Σ_i w_i θ_(i)
    Σ'   = Σ_i w_i (θ_(i) − μ)² [/ K] + damping
    damping' = (1 − τ_Σ)·damping + τ_Σ·Σ_limit
The fitness is the episode return, which is MAXIMISED: θ_(1) has the highest return.
"""

import chex
import jax
import jax.numpy as jnp


@chex.dataclass(frozen=True)
class CEMState:
    mean: jax.Array      # [P] μ of N(μ, Σ)
    var: jax.Array       # [P] diagonal of Σ
    damping: jax.Array   # [] additive noise on the variance
    elite: jax.Array     # [P] best actor of the last generation


def init(mean: jax.Array, sigma_init: float) -> CEMState:
    """Search distribution centred on `mean` with variance Σ_init; the elite is μ."""
    return CEMState(mean=mean, var=jnp.full_like(mean, sigma_init),
                    damping=jnp.asarray(sigma_init, mean.dtype), elite=mean)


def ask(key: jax.Array, state: CEMState, num: int) -> jax.Array:
    """`num` parameter vectors θ ~ N(μ, diag Σ): [num, P]."""
    noise = jax.random.normal(key, (num,) + state.mean.shape, state.mean.dtype)
    return state.mean + jnp.sqrt(state.var) * noise


def rank_weights(top_k: int) -> jax.Array:
    """w_i ∝ log(1 + K) − log(i) for ranks i = 1..K, summing to one."""
    raw = jnp.log(1.0 + top_k) - jnp.log(jnp.arange(1, top_k + 1, dtype=jnp.float32))
    return raw / raw.sum()


def tell(state: CEMState, population: jax.Array, fitness: jax.Array, *, top_k: int,
         sigma_limit: float, sigma_decay: float, divide_by_k: bool) -> CEMState:
    """Update (μ, Σ, damping, elite) from a population [N, P] and its returns [N] (maximised)."""
    order = jnp.argsort(-fitness)
    parents = population[order[:top_k]]
    weights = rank_weights(top_k).astype(population.dtype)
    mean = weights @ parents
    spread = weights @ jnp.square(parents - state.mean)
    if divide_by_k:
        spread = spread / top_k
    return CEMState(mean=mean, var=spread + state.damping,
                    damping=(1.0 - sigma_decay) * state.damping + sigma_decay * sigma_limit,
                    elite=population[order[0]])

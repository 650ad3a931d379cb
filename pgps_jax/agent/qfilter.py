"""Q-critic filtering (Algorithm 2): the TD3 critic pre-screens sampled actors.

Each candidate θ_j gets the potential P_j = E_{s ∈ SS_1}[Q1(s, π_θj(s))] (Section 4,
Proposition 1); the candidates with the highest P_j fill half the population. All M = SR·N
candidates are scored in one pass vmapped over actor parameters, the critic broadcast.
"""

from typing import Callable

import chex
import jax
import jax.numpy as jnp

# vmap axes of (flat actor parameters, critic parameters, states): candidates are batched,
# the shared critic and the sampled states are broadcast.
CANDIDATE_AXES = (0, None, None)


def potentials(actor_apply: Callable, critic_q1: Callable, candidates: jax.Array,
               critic_params: chex.ArrayTree, states: jax.Array) -> jax.Array:
    """P_j = mean_s Q1(s, π_j(s)) for candidates [M, P] on states [S, obs]: returns [M].

    actor_apply(flat_params, states) -> actions; critic_q1(critic_params, states, actions) -> [S].
    """
    def potential(flat, critic, obs):
        return jnp.mean(critic_q1(critic, obs, actor_apply(flat, obs)))

    return jax.vmap(potential, in_axes=CANDIDATE_AXES)(candidates, critic_params, states)


def select_best(candidates: jax.Array, scores: jax.Array, num: int) -> jax.Array:
    """The `num` candidates with the highest scores, best first: [num, P]."""
    _, best = jax.lax.top_k(scores, num)
    return candidates[best]

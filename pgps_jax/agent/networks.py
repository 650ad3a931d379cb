"""Actor and twin critic of TD3 (Table 2: hidden 400-300, ELU; tanh actor output).

The CEM searches over flat actor parameter vectors, so this module also provides the
flatten/unflatten pair that maps the actor's parameter tree to a vector and back.
"""

from typing import Callable, Sequence

import flax.linen as nn
from jax.flatten_util import ravel_pytree
import jax
import jax.numpy as jnp

# PyTorch's default Linear weights, U(±1/sqrt(fan_in)), which the paper's Σ_init was tuned with.
_torch_like_kernel = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")


def _dense(features: int) -> nn.Dense:
    return nn.Dense(features, kernel_init=_torch_like_kernel)


class Actor(nn.Module):
    """Deterministic policy π(s) ∈ [-1, 1]^action_size."""

    action_size: int
    hidden: Sequence[int] = (400, 300)

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = obs
        for width in self.hidden:
            x = nn.elu(_dense(width)(x))
        return jnp.tanh(_dense(self.action_size)(x))


class _QHead(nn.Module):
    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, action], axis=-1)
        for width in self.hidden:
            x = nn.elu(_dense(width)(x))
        return _dense(1)(x)[..., 0]


class TwinCritic(nn.Module):
    """Q1 and Q2 as one batched network: returns an array [2, ...] of Q-values."""

    hidden: Sequence[int] = (400, 300)

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        heads = nn.vmap(_QHead, variable_axes={"params": 0}, split_rngs={"params": True},
                        in_axes=None, out_axes=0, axis_size=2)
        return heads(self.hidden)(obs, action)


def first_q(critic: TwinCritic, params, obs: jax.Array, action: jax.Array) -> jax.Array:
    """Q1 alone, computing only the first head of the twin (actor loss, Q-filtering)."""
    head = jax.tree.map(lambda p: p[0], params["params"]["Vmap_QHead_0"])
    return _QHead(tuple(critic.hidden)).apply({"params": head}, obs, action)


def actor_flattener(actor: Actor, observation_size: int) -> tuple[int, Callable]:
    """(number of actor parameters, function mapping a flat vector to the parameter tree)."""
    shapes = jax.eval_shape(actor.init, jax.random.PRNGKey(0), jnp.zeros((observation_size,)))
    flat, unflatten = ravel_pytree(jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes))
    return flat.size, unflatten


def flatten(params) -> jax.Array:
    """The parameter tree as one vector (the CEM's search space)."""
    return ravel_pytree(params)[0]

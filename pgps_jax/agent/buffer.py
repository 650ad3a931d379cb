"""Device replay buffer: masked insertion of variable-length episodes, uniform sampling.

A ring buffer of fixed capacity holding (s, a, r, s', discount) rows. `add` takes a batch
of candidate transitions with a validity mask and writes only the valid ones, contiguously,
at the write pointer, so padded steps of episodes that ended early never enter the buffer.
Jit callers with the state donated so the arrays are updated in place.
"""

import chex
import jax
import jax.numpy as jnp


@chex.dataclass(frozen=True)
class Transition:
    obs: jax.Array        # [..., obs_size] s_t
    action: jax.Array     # [..., action_size] a_t
    reward: jax.Array     # [...] r_t
    next_obs: jax.Array   # [..., obs_size] s_{t+1}
    discount: jax.Array   # [...] 0 after a terminal (unhealthy) step, else 1 (truncation)


@chex.dataclass(frozen=True)
class BufferState:
    data: Transition      # every field has leading dimension [capacity]
    position: jax.Array   # [] int32, next row to write
    size: jax.Array       # [] int32, rows filled so far (≤ capacity)


def init(capacity: int, obs_size: int, action_size: int) -> BufferState:
    """An empty buffer of `capacity` rows."""
    if capacity <= 0:
        raise ValueError(f"buffer capacity must be a positive integer, got {capacity}")
    zeros = lambda *shape: jnp.zeros((capacity,) + shape, jnp.float32)
    data = Transition(obs=zeros(obs_size), action=zeros(action_size), reward=zeros(),
                      next_obs=zeros(obs_size), discount=zeros())
    return BufferState(data=data, position=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32))


def add(state: BufferState, batch: Transition, mask: jax.Array) -> BufferState:
    """Write the rows of `batch` where `mask` is true, in order; leading dims = mask.shape.

    A ring buffer: when full, the oldest rows are overwritten. At most `capacity` rows may be
    written by one call.
    """
    capacity = state.data.reward.shape[0]
    rows_in = jax.tree.map(lambda x: x.reshape((mask.size,) + x.shape[mask.ndim:]), batch)
    mask = mask.reshape(-1)
    offset = jnp.cumsum(mask.astype(jnp.int32)) - 1
    rows = jnp.where(mask, (state.position + offset) % capacity, capacity)  # capacity: dropped
    data = jax.tree.map(lambda buf, new: buf.at[rows].set(new, mode="drop"), state.data, rows_in)
    count = mask.sum(dtype=jnp.int32)
    return BufferState(data=data, position=(state.position + count) % capacity,
                       size=jnp.minimum(state.size + count, capacity))


def random_rows(state: BufferState, key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Row indices of `shape`, uniform (with replacement) over the filled part."""
    return jax.random.randint(key, shape, 0, jnp.maximum(state.size, 1))


def gather(state: BufferState, rows: jax.Array) -> Transition:
    """The transitions stored at `rows`."""
    return jax.tree.map(lambda buf: buf[rows], state.data)


def sample(state: BufferState, key: jax.Array, batch_size: int) -> Transition:
    """`batch_size` rows drawn uniformly (with replacement) from the filled part."""
    return gather(state, random_rows(state, key, (batch_size,)))


def sample_obs(state: BufferState, key: jax.Array, num: int) -> jax.Array:
    """`num` states s drawn uniformly from the filled part (SS_1, SS_2 of the paper)."""
    return state.data.obs[random_rows(state, key, (num,))]

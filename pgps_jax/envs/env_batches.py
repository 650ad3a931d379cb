"""Choosing, joining and slicing batches of env states, env by env.

A batch of states is a pytree whose leaves carry one row per env, except in a physics state
on MuJoCo Warp (`impl="warp"`): Warp keeps some arrays for the whole batch (e.g. its
contacts, which every physics step computes afresh). Those stay whole here, as in
`mjx.Data.where`: a choice keeps `on_false`'s, a join the first batch's, a slice all of them.
"""

from typing import Callable

import jax
import jax.numpy as jnp
from mujoco import mjx


def _is_physics(x) -> bool:
    return isinstance(x, mjx.Data)


def _per_env(data: mjx.Data):
    """The pytree of `data` with True at each leaf that has a row per env."""
    if data.impl != mjx.Impl.WARP:
        return jax.tree.map(lambda _: True, data)
    from mujoco.mjx._src.types import tree_path_to_attr_str
    from mujoco.mjx.warp import types as warp_types
    batched = warp_types._BATCH_DIM["Data"]  # MJX's own table, what `Data.where` reads
    # (private in mujoco-mjx 3.17; tests/test_warp_physics.py fails if it moves)
    return jax.tree_util.tree_map_with_path(
        lambda path, _: batched.get(tree_path_to_attr_str(path), True), data)


def _rowwise(fn: Callable, whole: Callable, tree, *rest):
    """fn(leaf, *rest_leaves) on every leaf with a row per env; whole(leaf, *rest_leaves)
    on a Warp physics state's leaves of the whole batch."""
    def node(x, *others):
        if not _is_physics(x):
            return fn(x, *others)
        return jax.tree.map(lambda per_env, *leaves: (fn if per_env else whole)(*leaves),
                            _per_env(x), x, *others)
    return jax.tree.map(node, tree, *rest, is_leaf=_is_physics)


def select(pred: jax.Array, on_true, on_false):
    """Per env, `on_true` where `pred` [B] holds, else `on_false` (batches of B envs); a
    scalar `pred` chooses for all of them."""
    def pick(a, b):
        return jnp.where(pred.reshape(pred.shape + (1,) * (a.ndim - pred.ndim)), a, b)
    return _rowwise(pick, lambda a, b: b, on_true, on_false)


def concatenate(first, second):
    """The envs of `first`, then those of `second`, as one batch."""
    return _rowwise(lambda a, b: jnp.concatenate([a, b]), lambda a, b: a, first, second)


def rows(batch, start: int, stop: int | None = None):
    """The envs `start` to `stop` (exclusive; None: to the end) of `batch`."""
    return _rowwise(lambda x: x[start:stop], lambda x: x, batch)

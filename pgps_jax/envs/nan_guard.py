"""Ends an episode whose physics went non-finite, so no NaN reaches the learner.

A step whose physics state, observation or reward is not finite becomes terminal
(`done=1`, `metrics["unstable"]=1`, reward 0) and keeps the previous, finite physics state,
observation and metrics, so later (vmapped) steps of that env stay finite. The rollout never
stores a transition flagged unstable.
"""

from brax.envs.base import State
import jax
import jax.numpy as jnp

from pgps_jax.envs import env_batches


def all_finite(*trees) -> jax.Array:
    """True iff every floating-point leaf of `trees` is finite (a scalar bool)."""
    leaves = [x for x in jax.tree.leaves(trees) if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def guard(prev: State, new: State, finite: jax.Array) -> State:
    """Returns `new`, or, where `finite` is False, `prev` flagged terminal with reward 0."""
    def keep(a, b):
        return jnp.where(finite, a, b)

    metrics = {k: keep(v, prev.metrics.get(k, jnp.zeros_like(v))) for k, v in new.metrics.items()}
    metrics["unstable"] = keep(0.0, 1.0).astype(jnp.float32)
    return new.replace(
        pipeline_state=env_batches.select(~finite, prev.pipeline_state, new.pipeline_state),
        obs=keep(new.obs, prev.obs),
        reward=keep(new.reward, 0.0),
        done=keep(new.done, 1.0),
        metrics=metrics,
    )

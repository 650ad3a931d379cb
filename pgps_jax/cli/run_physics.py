"""The physics of a training run: its `physics.*` settings (`make_env`'s keyword arguments;
null: the task's own), recorded in the run's configuration as the env simulates them, so that
a run resumes on the physics it started on whatever the defaults have become since.

Imported once the command line has been read: it loads MuJoCo and JAX.
"""

from typing import Any, Mapping, Optional

from pgps_jax.cli.assignments import ENV_FIELDS, checked_env_kwargs
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import make_env
from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.physics import SPEED_ONLY

BEFORE_RECORDED = {"matmul_precision": "default"}
"""How a run configured before `physics.*` existed simulated, where today's default differs:
the physics' matrix products at JAX's default precision (TF32 on a GPU)."""

IDENTITY_KEYS = tuple(f"physics.{name}" for name in ENV_FIELDS if name not in SPEED_ONLY)
"""The physics settings a checkpoint resumes only under: those that change what is simulated,
not how it is computed (`physics.SPEED_ONLY`)."""


def given(node: Mapping[str, Any]) -> dict:
    """The settings of a `physics:` node that are set (not null), checked as `make_env`
    checks them (UsageError naming the setting)."""
    return checked_env_kwargs({k: v for k, v in node.items() if v is not None}, "physics")


def env_for(task: str, node: Mapping[str, Any]):
    """The env of `task` with the physics of a `physics:` node."""
    kwargs = given(node)
    if kwargs and not isinstance(make_env(task), MjxEnv):
        raise UsageError(f"env={task} has no MJX physics: physics.* settings apply to "
                         f"MuJoCo tasks only (got physics.{next(iter(kwargs))})")
    try:
        return make_env(task, **kwargs)
    except ValueError as e:
        raise UsageError(f"physics: {e}") from None


def recorded(task: str, node: Mapping[str, Any]) -> dict:
    """The `physics:` node to record for a run of `task` configured with `node`: every field,
    those the env simulates with (`MjxEnv.settings`) at the values it simulates them, those
    that only change how it computes as set (null: the platform's default)."""
    env = env_for(task, node)
    return ({name: None for name in ENV_FIELDS} | given(node)
            | (env.settings() if isinstance(env, MjxEnv) else {}))


def as_run(task: str, node: Optional[Mapping[str, Any]]) -> dict:
    """A saved run's `physics:` node: as recorded, or (None) for a run configured before
    physics was recorded, the task's physics of today but for `BEFORE_RECORDED`."""
    if node is not None:
        return recorded(task, node)
    today = recorded(task, {})
    return today | (BEFORE_RECORDED if isinstance(make_env(task), MjxEnv) else {})

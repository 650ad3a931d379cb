"""The physics of a training run: its `physics.*` settings (`make_env`'s keyword arguments;
null: the task's own), recorded in the run's configuration as the env simulates them, so that
a run resumes on the physics it started on whatever the defaults have become since.

Imported once the command line has been read: it loads MuJoCo and JAX.
"""

import sys
from typing import Any, Mapping, Optional

from pgps_jax.cli.assignments import ENV_FIELDS, checked_env_kwargs
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import TASKS, make_env
from pgps_jax.envs.physics import SPEED_ONLY

IDENTITY_KEYS = tuple(f"physics.{name}" for name in ENV_FIELDS if name not in SPEED_ONLY)
"""The physics settings a checkpoint resumes only under: those that change what is simulated,
not how it is computed (`physics.SPEED_ONLY`)."""

UNRECORDED = ("does not record its physics (a run from before the training command recorded "
              "it), and the defaults have changed since: the physics' matrix products were "
              "at JAX's default precision before they became float32 "
              "(physics.matmul_precision=default), and halfcheetah's, walker2d's and the ant's "
              "Newton iterations were fewer before (physics.iterations)")
"""Why the physics of a run configured before `physics.*` existed cannot be told."""


def given(node: Mapping[str, Any]) -> dict:
    """The settings of a `physics:` node that are set (not null), checked as `make_env`
    checks them (UsageError naming the setting)."""
    return checked_env_kwargs({k: v for k, v in node.items() if v is not None}, "physics.")


def env_for(task: str, node: Mapping[str, Any]):
    """The env of `task` with the physics of a `physics:` node."""
    return _env(task, given(node))


def _env(task: str, kwargs: dict):
    if kwargs and task not in TASKS:
        raise UsageError(f"env={task} has no MJX physics: physics.* settings apply to the "
                         f"MuJoCo tasks ({', '.join(TASKS)}); got physics.{next(iter(kwargs))}")
    try:
        return make_env(task, **kwargs)
    except ValueError as e:
        raise UsageError(f"physics: {e}") from None


def recorded(task: str, node: Mapping[str, Any]) -> dict:
    """The `physics:` node to record for a run of `task` configured with `node`: every field,
    those the env simulates with (`MjxEnv.settings`) at the values it simulates them, those
    that only change how it is computed as set (null: the platform's default)."""
    kwargs = given(node)
    env = _env(task, kwargs)
    simulated = env.settings() if task in TASKS else {}
    return {name: None for name in ENV_FIELDS} | kwargs | simulated


def run_env(run_dir: str, task: str, node: Optional[Mapping[str, Any]]):
    """The env of a saved run of `task` (`evaluate`, `render`): on its recorded physics, or,
    for a run that does not record it, on the task's of today, with a warning."""
    if node is None and task in TASKS:
        print(f"warning: {run_dir} {UNRECORDED}; using the task's physics of today",
              file=sys.stderr)
    return env_for(task, node or {})

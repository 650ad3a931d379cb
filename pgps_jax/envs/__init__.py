"""The tasks by name: the five MuJoCo locomotion tasks on MJX and a point mass for tests.

`make_env(name, **kwargs)` builds one; for a MuJoCo task the keyword arguments override its
solver settings (fields of `physics.Physics`).
"""

import functools
import importlib

importlib.import_module("pgps_jax.envs.quiet_mjx")  # before brax, which imports mujoco.mjx

from brax.envs.base import Env, State  # the Env contract, re-exported

from pgps_jax.envs.ant import Ant
from pgps_jax.envs.half_cheetah import HalfCheetah
from pgps_jax.envs.hopper import Hopper
from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.point import PointMass
from pgps_jax.envs.swimmer import Swimmer
from pgps_jax.envs.walker2d import Walker2d

_REGISTRY = {
    "halfcheetah": HalfCheetah,
    "hopper": Hopper,
    "walker2d": Walker2d,
    "ant": Ant,
    "swimmer": Swimmer,
    "point": PointMass,
}
__all__ = ["Env", "State", "TASKS", "ALL_TASKS", "make_env"]

TASKS = ("halfcheetah", "hopper", "walker2d", "ant", "swimmer")
"""The MuJoCo tasks (the registry also holds "point")."""
ALL_TASKS = tuple(_REGISTRY)
"""Every name `make_env` takes: the MuJoCo tasks and the point mass."""


def make_env(name: str, **kwargs) -> Env:
    """Builds the task `name`; raises ValueError listing the tasks if it is unknown. Equal
    settings give the same (immutable) env object, for a MuJoCo task whether given or left to
    its defaults, so that agents of equal settings share their compiled programs within a
    process (`pgps_jax.cli.loop`) and a run's recorded physics builds no second env."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}; available tasks: {', '.join(_REGISTRY)}")
    env_class = _REGISTRY[name]
    if issubclass(env_class, MjxEnv):
        kwargs = env_class.constructor_arguments(**kwargs)
    return _built(name, tuple(sorted(kwargs.items())))


@functools.lru_cache(maxsize=32)
def _built(name: str, kwargs: tuple) -> Env:
    return _REGISTRY[name](**dict(kwargs))

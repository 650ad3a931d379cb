"""`NAME=VALUE` options (`--set`, `--eval`, `--env`) of the experiment and benchmark commands,
read with the types of the fields they name, as the training command line reads its own."""

import dataclasses
import typing

import yaml

from pgps_jax.cli.errors import UsageError
from pgps_jax.cli.run_config import coerce
from pgps_jax.envs.mjx_env import check_start_pose
from pgps_jax.envs.physics import Physics

ENV_FIELDS = {"start_pose": str, **typing.get_type_hints(Physics)}
"""The keyword arguments of `make_env` for a MuJoCo task and their types: the pose reset
starts from and the `Physics` fields."""


def field_types(fields: type) -> dict:
    """A dataclass's fields and their types, in their order."""
    types = typing.get_type_hints(fields)
    return {f.name: types[f.name] for f in dataclasses.fields(fields)}


def assignments(pairs: list[str], what: str, hints: dict) -> dict:
    """`name=value` pairs as the types of `hints` (values read as YAML, as on the training
    command line: true, 400, [64,64]); a UsageError names `what` and the valid names."""
    values = {}
    for pair in pairs:
        name, sep, text = pair.partition("=")
        if not sep or name not in hints:
            raise UsageError(f"{what} {pair!r}: expected NAME=VALUE with NAME one of "
                             f"{', '.join(hints)}")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            value = text
        if isinstance(value, str):  # YAML reads 1e-3 as text
            try:
                value = float(value)
            except ValueError:
                pass
        values[name] = coerce(f"{what} {name}", value, hints[name])
    return values


def env_assignments(pairs: list[str], what: str = "--env") -> dict:
    """`make_env` keyword arguments from `name=value` pairs, their values checked as `make_env`
    would check them (a UsageError instead of its ValueError)."""
    return checked_env_kwargs(assignments(pairs, what, ENV_FIELDS), f"{what} ")


def checked_env_kwargs(values: dict, prefix: str) -> dict:
    """`values` (`make_env` keyword arguments) of the types `ENV_FIELDS` names and valid
    together, or a UsageError naming the setting as typed, `prefix` + name ("--env iterations",
    "physics.iterations")."""
    unknown = sorted(set(values) - set(ENV_FIELDS))
    if unknown:
        raise UsageError(f"{prefix}{unknown[0]}: not a physics setting; valid: "
                         f"{', '.join(ENV_FIELDS)}")
    values = {name: coerce(f"{prefix}{name}", value, ENV_FIELDS[name])
              for name, value in values.items()}
    physics = {name: value for name, value in values.items() if name != "start_pose"}
    try:
        Physics(**physics)
        if "start_pose" in values:
            check_start_pose(values["start_pose"])
    except ValueError as e:
        raise UsageError(f"{prefix.rstrip(' .')}: {e}") from None
    return values

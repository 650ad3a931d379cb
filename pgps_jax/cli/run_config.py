"""The configuration of a training run: Hydra's composed YAML -> (RunSettings, PGPSConfig).

The YAML in `configs/` is composed by Hydra once, checked here, and turned into two frozen
objects: `RunSettings` (what the training script does: budget, evaluation period, run
directory, checkpoints) and `PGPSConfig` (the algorithm). The algorithm never sees Hydra.

Every error is a `UsageError` whose message names the setting and says what is valid.
"""

import dataclasses
import math
import pathlib
import typing
from typing import Any, Iterable, Mapping, Optional, Sequence

from pgps_jax.agent.config import SWITCHES, EvaluationConfig, PGPSConfig, check_for_algorithm
from pgps_jax.cli.errors import UsageError
from pgps_jax.field_types import mismatch

CONFIG_DIR = pathlib.Path(__file__).resolve().parents[2] / "configs"
"""`configs/` at the repository top level (the package is installed editable)."""

PGPS_FIELDS = tuple(f.name for f in dataclasses.fields(PGPSConfig))

IDENTITY_KEYS = (("env.name", "algo.name", "seed", "eval_every", "eval_episodes", "eval_steps")
                 + tuple(f"pgps.{f}" for f in PGPS_FIELDS))
"""Settings that fix a run's trajectory and its evaluation rows: a checkpoint is resumed only
under the same values. The others (budget, checkpoint period, paths, progress bar) may change."""


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """What `python -m pgps_jax.train` does besides the algorithm (configs/config.yaml)."""

    env: str
    """Task name (`env=<task>`, `configs/env/<task>.yaml`)."""
    algo: str
    """Algorithm (`algo=<name>`, `configs/algo/<name>.yaml`): PGPS or a baseline."""
    seed: int
    """PRNG seed; evaluation uses PRNGKey(seed + 100)."""
    total_steps: int
    """Env-step budget, random warm-up included, evaluation excluded."""
    eval_every: int
    """Evaluate μ, the TD3 actor and the elite each time the env steps cross a multiple of
    this (and at the start and the end)."""
    eval_episodes: int
    """Deterministic test episodes per evaluated actor."""
    eval_steps: int
    """Step limit of a test episode."""
    checkpoint_every: Optional[int]
    """Generations between checkpoints, besides `checkpoint_every_s`; None: by time alone (one
    is also written at the end and on Ctrl-C)."""
    checkpoint_every_s: Optional[float]
    """Seconds of the run between checkpoints: an interrupted run loses at most this much (and
    the generation under way). A checkpoint writes the whole replay buffer. None: by
    generations alone (runs from before this setting)."""
    keep_checkpoints: int
    """Most recent checkpoints kept."""
    output_dir: str
    """Root of the run directories."""
    run_dir: str
    """This run's directory."""
    resume: bool | str
    """False, True (continue `run_dir`) or the path of a run directory to continue."""
    progress: bool
    """Show a progress bar."""
    physics: Optional[Mapping[str, Any]] = None
    """The `physics:` node (`make_env`'s arguments; null: the task's own) as configured; a
    planned run's holds every field as recorded (`pgps_jax.cli.run_physics.recorded`); None
    for a saved run from before the record."""

    @property
    def evaluation(self) -> EvaluationConfig:
        """The test evaluation's settings (Section 5.1)."""
        return EvaluationConfig(every=self.eval_every, episodes=self.eval_episodes,
                                steps=self.eval_steps)


_RUN_KEYS = tuple(f.name for f in dataclasses.fields(RunSettings)
                  if f.name not in ("env", "algo", "physics"))


def pgps_defaults() -> dict:
    """PGPSConfig's defaults (Table 3) as a plain dict (tuples as lists), for Hydra."""
    return {f.name: list(f.default) if isinstance(f.default, tuple) else f.default
            for f in dataclasses.fields(PGPSConfig)}


def register_structured_configs() -> None:
    """Registers `pgps/table3` (PGPSConfig's defaults) in Hydra's ConfigStore."""
    from hydra.core.config_store import ConfigStore
    ConfigStore.instance().store(group="pgps", name="table3", node=pgps_defaults())


def env_choices() -> list[str]:
    """The tasks with a `configs/env/<task>.yaml`."""
    return sorted(p.stem for p in (CONFIG_DIR / "env").glob("*.yaml"))


def algo_choices() -> list[str]:
    """The algorithms with a `configs/algo/<name>.yaml`."""
    return sorted(p.stem for p in (CONFIG_DIR / "algo").glob("*.yaml"))


def physics_fields() -> list[str]:
    """The `physics.<field>` settings of `configs/config.yaml` (`make_env`'s arguments), read
    without loading the physics."""
    import yaml
    return list(yaml.safe_load((CONFIG_DIR / "config.yaml").read_text())["physics"])


def _valid_settings_text() -> str:
    return ("valid settings: env=<task>, algo=<name>, " + ", ".join(_RUN_KEYS)
            + ", pgps.<field>, physics.<field> (run with --cfg job to see them all)")


def parse_overrides(args: Sequence[str]) -> list:
    """Hydra's parse of the `key=value` arguments (flags and their values left out), or a
    UsageError saying what cannot be parsed."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    candidates = [a for a in args if "=" in a and not a.startswith("-")]
    try:
        return OverridesParser.create().parse_overrides(candidates)
    except OverrideParseException as e:
        raise UsageError(f"cannot parse the command line: {e}") from None


_HYDRA_FLAGS_WITH_VALUES = ("--cfg", "-c", "--package", "-p", "--config-name", "-cn",
                            "--config-path", "-cp", "--config-dir", "-cd", "--info", "-i")
"""Hydra's flags that take a value: the word after one is not a setting."""


def _require_one_of(override, what: str, choices: Sequence[str]) -> None:
    """UsageError unless the override (env=, algo=) names one of `choices`."""
    key, value = override.key_or_group, override.value()
    if not isinstance(value, str):  # a list, or a sweep
        raise UsageError(f"{override.input_line}: {key}= takes one {what} of: "
                         f"{', '.join(choices)}")
    if value not in choices:
        raise UsageError(f"unknown {key} {value!r}; choices: {', '.join(choices)}")


def check_overrides(args: Sequence[str]) -> None:
    """Checks command-line overrides before Hydra composes them: unknown keys, tasks and
    algorithms, words that are not key=value, and PGPS's couplings set for a baseline.

    Hydra would reject an unknown key too, but without saying what is valid.
    """
    for i, arg in enumerate(args):  # a flag's value (--cfg job) follows its flag
        if ("=" not in arg and not arg.startswith(("-", "~"))
                and not (i and args[i - 1] in _HYDRA_FLAGS_WITH_VALUES)):
            raise UsageError(f"{arg!r} is not a setting: write key=value; "
                             f"{_valid_settings_text()}")
    algo, pgps_fields = "pgps", []  # for the couplings' check, after the loop
    for o in parse_overrides(args):
        key = o.key_or_group
        if key.startswith("hydra") or key in _RUN_KEYS:
            continue
        if key == "env":
            _require_one_of(o, "task", env_choices())
            continue
        if key == "env.name":
            raise UsageError("set the task with env=<task>, not env.name "
                             f"(choices: {', '.join(env_choices())})")
        if key == "algo":
            _require_one_of(o, "algorithm", algo_choices())
            algo = o.value()
            continue
        if key.startswith("algo."):
            raise UsageError("set the algorithm with algo=<name>, not algo.name "
                             f"(choices: {', '.join(algo_choices())})")
        if key == "pgps":
            value = o.value()
            unknown = (sorted(set(value) - set(PGPS_FIELDS)) if isinstance(value, dict)
                       else [] if value == "table3" else None)  # table3: the defaults' group
            if unknown != []:
                raise UsageError(f"pgps={o.input_line.split('=', 1)[1]} is not a setting: set "
                                 f"PGPSConfig's fields as pgps.<field>=value, one of: "
                                 f"{', '.join(PGPS_FIELDS)}")
            pgps_fields += list(value) if isinstance(value, dict) else []
            continue
        if key.startswith("physics."):
            if key[len("physics."):] not in physics_fields():
                raise UsageError(f"unknown setting {key!r}; physics.<field> must be one of: "
                                 f"{', '.join(physics_fields())}")
            continue
        if key.startswith("pgps."):
            field = key[len("pgps."):]
            if field in _RUN_KEYS:
                raise UsageError(f"{key} is not a PGPSConfig field: set {field}=... (a setting "
                                 "of the run, like the test evaluation's)")
            if field not in PGPS_FIELDS:
                raise UsageError(f"unknown setting {key!r}: PGPSConfig has no field {field!r}; "
                                 f"pgps.<field> must be one of: {', '.join(PGPS_FIELDS)}")
            pgps_fields.append(field)
            continue
        raise UsageError(f"unknown setting {key!r}; {_valid_settings_text()}")
    couplings = [f for f in pgps_fields if f in SWITCHES]
    if algo != "pgps" and couplings:
        raise UsageError(f"pgps.{couplings[0]} is one of PGPS's couplings "
                         f"({', '.join(SWITCHES)}); algo={algo} has none of them, they "
                         f"apply to algo=pgps")


def coerce(key: str, value: Any, kind: Any) -> Any:
    """`value` as the dataclass field type `kind`, or a UsageError naming `key`: None for an
    `Optional` field; an integral number as an int, an integer as a float, a list or tuple as
    a tuple of layer widths, a non-empty string as itself; a bool as itself. Strict checks by
    `field_types.mismatch`."""
    optional = [k for k in typing.get_args(kind) if k is not type(None)]
    if typing.get_origin(kind) is typing.Union and len(optional) == 1:  # Optional[X]
        return None if value is None else coerce(key, value, optional[0])
    if kind is int and isinstance(value, float) and value.is_integer():
        return int(value)
    if kind is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise UsageError(f"{key} must be a number, got {value!r}")
    if typing.get_origin(kind) is tuple:
        if isinstance(value, (list, tuple)):
            return tuple(coerce(f"{key}[{i}]", v, int) for i, v in enumerate(value))
        raise UsageError(f"{key} must be a list of layer widths like [400,300], got {value!r}")
    if kind is str and value == "":
        raise UsageError(f"{key} must be a non-empty string, got {value!r}")
    expected = mismatch(value, kind)
    if expected:
        raise UsageError(f"{key} must be {expected}, got {value!r}")
    return int(value) if kind is int else value


def pgps_config(values: Mapping[str, Any]) -> PGPSConfig:
    """The `pgps:` node as a validated PGPSConfig (unknown keys and bad values rejected)."""
    unknown = sorted(set(values) - set(PGPS_FIELDS))
    if unknown:
        raise UsageError(f"unknown setting pgps.{unknown[0]}; pgps.<field> must be one of: "
                         f"{', '.join(PGPS_FIELDS)}")
    hints = typing.get_type_hints(PGPSConfig)
    kwargs = {name: coerce(f"pgps.{name}", value, hints[name]) for name, value in values.items()}
    try:
        return PGPSConfig(**kwargs)
    except ValueError as e:
        raise UsageError(f"invalid pgps setting: {e}") from None


RUN_VALUES_BEFORE_ADDED = {"checkpoint_every_s": None}
"""Top-level settings added since runs were first saved, at the behaviour from before them: a
saved run's configuration without `checkpoint_every_s` checkpointed by generations alone."""


def run_settings(values: Mapping[str, Any]) -> RunSettings:
    """The top-level settings (everything but `pgps:`) as validated RunSettings; those of
    `RUN_VALUES_BEFORE_ADDED` that a saved run lacks take their value from before them."""
    values = {**RUN_VALUES_BEFORE_ADDED, **values}
    known = set(_RUN_KEYS) | {"env", "algo", "pgps"}
    unknown = sorted(set(values) - known - {"physics"})  # absent from runs before it existed
    if unknown:
        raise UsageError(f"unknown setting {unknown[0]!r}; {_valid_settings_text()}")
    missing = sorted(known - set(values))
    if missing:
        raise UsageError(f"missing setting {missing[0]!r}")
    env = values["env"]
    name = env.get("name") if isinstance(env, Mapping) else None
    if name not in env_choices():
        raise UsageError(f"unknown env {name!r}; choices: {', '.join(env_choices())}")
    algo = values["algo"]
    algo = algo.get("name") if isinstance(algo, Mapping) else None
    if algo not in algo_choices():
        raise UsageError(f"unknown algo {algo!r}; choices: {', '.join(algo_choices())}")
    hints = typing.get_type_hints(RunSettings)
    kwargs = {}
    for key in _RUN_KEYS:
        value = values[key]
        if key == "resume":
            if not isinstance(value, (bool, str)) or value == "":
                raise UsageError(f"resume must be true, false or a run directory, got {value!r}")
            kwargs[key] = value
        else:
            kwargs[key] = coerce(key, value, hints[key])
    for key, low in (("seed", 0), ("total_steps", 1), ("eval_every", 1), ("eval_episodes", 1),
                     ("eval_steps", 1), ("checkpoint_every", 1), ("keep_checkpoints", 1)):
        if kwargs[key] is not None and kwargs[key] < low:
            raise UsageError(f"{key}={kwargs[key]} is invalid: must be an integer >= {low}"
                             + (", or null" if key == "checkpoint_every" else ""))
    every_s = kwargs["checkpoint_every_s"]
    if every_s is not None and not 0 < every_s < math.inf:
        raise UsageError(f"checkpoint_every_s={every_s} is invalid: must be a positive number "
                         "of seconds, or null")
    if every_s is None and kwargs["checkpoint_every"] is None:
        raise UsageError("checkpoint_every and checkpoint_every_s are both null: set one, or "
                         "the run checkpoints only at its end")
    physics = values.get("physics")
    if physics is not None and not isinstance(physics, Mapping):
        raise UsageError(f"physics must be a mapping of physics.<field> settings, got "
                         f"{physics!r}")
    return RunSettings(env=name, algo=algo, physics=physics, **kwargs)


def from_dict(values: Mapping[str, Any]) -> tuple[RunSettings, PGPSConfig]:
    """The composed configuration (a plain dict, resolved) as (RunSettings, PGPSConfig)."""
    pgps_values = values.get("pgps")
    if not isinstance(pgps_values, Mapping):
        raise UsageError("missing the pgps: node of the configuration")
    return run_settings(values), pgps_config(pgps_values)


def require_training(run: RunSettings, config: PGPSConfig) -> None:
    """UsageError unless the algorithm can run with `config` and the budget leaves steps for
    generations after the random warm-up."""
    try:
        check_for_algorithm(run.algo, config)
    except ValueError as e:
        raise UsageError(f"algo={run.algo}: {e}") from None
    if run.total_steps <= config.warmup_steps:
        raise UsageError(f"total_steps={run.total_steps} does not exceed the random warm-up "
                         f"(pgps.warmup_steps={config.warmup_steps}): no generation would train; "
                         f"set total_steps above {config.warmup_steps}")


def flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dict -> {"a.b": value}; lists and tuples are leaves (as lists)."""
    flat = {}
    for key, value in values.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, path + "."))
        else:
            flat[path] = list(value) if isinstance(value, tuple) else value
    return flat


def differences(saved: Mapping[str, Any], now: Mapping[str, Any],
                keys: Iterable[str]) -> list[str]:
    """'key: checkpoint X, now Y' for each of `keys` whose value differs."""
    saved_flat, now_flat = flatten(saved), flatten(now)
    missing = object()
    lines = []
    for key in keys:
        a, b = saved_flat.get(key, missing), now_flat.get(key, missing)
        if a != b or type(a) is not type(b) and not _same_number(a, b):
            show = lambda v: "(absent)" if v is missing else repr(v)
            lines.append(f"{key}: checkpoint {show(a)}, now {show(b)}")
    return lines


def _same_number(a: Any, b: Any) -> bool:
    numbers = (int, float)
    return (isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool)
            and not isinstance(b, bool) and a == b)


def override_keys(overrides: Iterable[str]) -> list[str]:
    """The keys (or groups) set by command-line overrides like 'env=hopper', 'pgps.x=1'."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    return [o.key_or_group for o in parsed]


def explicitly_set(key: str, explicit: Iterable[str]) -> bool:
    """Whether `key` ("pgps.pop_size") is covered by one of the override keys ("pgps", "env")."""
    return any(key == e or key.startswith(e + ".") for e in explicit) or (
        key == "env.name" and "env" in explicit)

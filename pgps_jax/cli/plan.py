"""What a training invocation will do, decided before anything is trained or written: a new
run, or the resumption of one (`plan`)."""

import copy
import dataclasses
import sys
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

from pgps_jax.agent.config import PGPSConfig, effective_fields, values_before_added
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.errors import UsageError
from pgps_jax.cli.run_config import (IDENTITY_KEYS, RunSettings, differences, explicitly_set,
                                     flatten, from_dict, override_keys, require_training)


@dataclasses.dataclass(frozen=True)
class Plan:
    """What a training invocation will do, decided before anything is trained."""

    run: RunSettings
    config: PGPSConfig
    resolved: dict
    """The resolved configuration (saved in the run directory and in every checkpoint)."""
    directory: rundir.RunDir
    lock: rundir.RunLock
    """Held from planning to the end of training: no other process trains in `directory`."""
    resume_step: Optional[int]
    """The newest checkpoint (generation) whose metadata reads, or None for a new run; the
    trainer continues from it, or from an older one if it fails verification."""


def _set(values: dict, dotted: str, value: Any) -> None:
    node = values
    *parents, last = dotted.split(".")
    for part in parents:
        node = node.setdefault(part, {})
    node[last] = value


def _checkpointed(directory: rundir.RunDir) -> tuple[int, dict]:
    """(newest readable checkpoint's generation, its metadata: the resolved configuration
    saved with it, the env steps taken); checkpoints whose metadata cannot be read are set
    aside."""
    from pgps_jax.cli.checkpoint import Checkpoints
    checkpoints = Checkpoints(directory.checkpoints)
    try:
        return checkpoints.latest_meta()
    finally:
        checkpoints.close()


def _require_budget_not_below(run: RunSettings, saved: dict, taken: int, step: int) -> None:
    """A resumed run's total_steps may not fall below the env steps its checkpoint has
    taken, unless it is the budget the run already reached (resuming a finished run)."""
    if run.total_steps < taken and run.total_steps != saved.get("total_steps"):
        raise UsageError(
            f"total_steps={run.total_steps} is below the {taken:,} env steps that the "
            f"checkpoint (generation {step}) has taken; a run cannot be shortened. Give "
            f"total_steps >= {taken} to continue it.")


def _with_new_fields(saved: dict) -> dict:
    """A checkpoint's configuration with the settings added since it was written set to the
    behaviour from before them: PGPS, and the PGPSConfig fields at `values_before_added`
    (where that is not a field's default, such a checkpoint resumes by directory, or with
    resume=true and the old value set)."""
    saved = copy.deepcopy(saved)
    saved.setdefault("algo", {"name": "pgps"})
    pgps = saved.setdefault("pgps", {})
    for name, value in values_before_added().items():
        pgps.setdefault(name, value)
    return saved


def _recorded_physics(task: str, values: dict) -> dict:
    """The `physics:` node to record for a run of `task` (`run_physics.recorded`)."""
    from pgps_jax.cli import run_physics
    return run_physics.recorded(task, values.get("physics") or {})


def _recording_physics(run: RunSettings, values: dict) -> RunSettings:
    """`run` of a new run, its `physics:` node replaced in it and in `values` by the one to
    record."""
    values["physics"] = _recorded_physics(run.env, values)
    return dataclasses.replace(run, physics=values["physics"])


def _physics_differences(directory: rundir.RunDir, saved: dict, effective: dict,
                         overrides: Sequence[str]) -> list[str]:
    """The `physics.*` settings in which `effective`'s recorded physics differs from the
    checkpoint's; a checkpoint of a MuJoCo task that does not record its physics is refused
    unless the command states it (which the resumed run then records)."""
    from pgps_jax.cli import run_physics
    if saved.get("physics") is None:
        stated = any(k == "physics" or k.startswith("physics.")
                     for k in override_keys(overrides))
        if effective["env"]["name"] in run_physics.TASKS and not stated:
            raise UsageError(f"the checkpoint in {directory.checkpoints} "
                             f"{run_physics.UNRECORDED}. Resume with the physics.* settings "
                             f"it ran with; the resumed run records them.")
        return []
    return differences(saved, effective, run_physics.IDENTITY_KEYS)


def _comparable(values: dict) -> dict:
    """A run's settings with the PGPSConfig fields that cannot act under the others left out
    (`effective_fields`), for comparing a checkpoint's with the command's."""
    return {**values, "pgps": effective_fields(values.get("pgps", {}))}


def plan(values: Mapping[str, Any], overrides: Sequence[str] = ()) -> Plan:
    """Decides between a new run and a resumed one; raises UsageError before any training.

    resume=false: a new run in run_dir, which must not hold one already.
    resume=true: continue run_dir's latest checkpoint (a new run if it has none); the
      settings in IDENTITY_KEYS must equal the checkpoint's.
    resume=<dir>: continue <dir> with its checkpointed settings; settings given on the command
      line replace them, and must not change any in IDENTITY_KEYS.
    Either way the physics the run simulates is recorded and must equal the checkpoint's
    (`run_physics.IDENTITY_KEYS`).
    """
    values = copy.deepcopy(dict(values))
    resume = values.get("resume")
    by_path = isinstance(resume, str) and resume != ""
    if by_path:  # its settings are checked once merged with the checkpoint's
        run, config = None, None
        directory = rundir.RunDir(resume)
        if not directory.path.is_dir():
            raise UsageError(f"resume={resume}: no such run directory")
        _require_no_other_directory(resume, values, overrides)
    else:
        run, config = from_dict(values)
        if run.resume is False:
            return _plan_new(run, config, values)
        directory = rundir.RunDir(run.run_dir)
    directory.ensure_writable()
    lock = directory.lock()
    try:
        return _plan_resume(run, config, values, overrides, directory, lock)
    except BaseException:
        lock.release()
        raise


def _require_no_other_directory(resume: str, values: Mapping[str, Any],
                                overrides: Sequence[str]) -> None:
    """resume=<dir> continues the run in <dir>: a run_dir naming another directory, or an
    output_dir (where new runs go), given beside it is refused rather than ignored."""
    keys = override_keys(overrides)
    if "output_dir" in keys:
        other = "output_dir"
    elif "run_dir" in keys and Path(values["run_dir"]).resolve() != Path(resume).resolve():
        other = "run_dir"
    else:
        return
    raise UsageError(f"resume={resume} continues the run in that directory; {other}="
                     f"{values[other]} beside it would be ignored. Give resume=<dir> alone, "
                     f"or resume=true with run_dir=<dir>.")


def _plan_new(run: RunSettings, config: PGPSConfig, values: dict) -> Plan:
    """`plan` for resume=false: a new run in run_dir, which must not hold one already."""
    require_training(run, config)
    run = _recording_physics(run, values)
    directory = rundir.RunDir(run.run_dir)
    directory.ensure_writable()
    lock = directory.lock()
    if directory.holds_run():
        lock.release()
        raise UsageError(
            f"{directory.path} already holds a run; continue it with resume=true, or "
            f"choose another directory with run_dir=... (or output_dir=...)")
    return Plan(run, config, values, directory, lock, None)


def _plan_resume(run: Optional[RunSettings], config: Optional[PGPSConfig], values: dict,
                 overrides: Sequence[str], directory: rundir.RunDir,
                 lock: rundir.RunLock) -> Plan:
    """`plan` for resume=true (`run` and `config` the command's) or resume=<dir> (None: the
    checkpoint's, with the command's settings merged in), once the directory is locked."""
    by_path = run is None
    if not directory.has_checkpoint():
        if by_path:
            raise UsageError(f"resume={values['resume']}: {directory.checkpoints} holds no "
                             f"checkpoint")
        require_training(run, config)
        print(f"resume=true: no checkpoint in {directory.path}; starting a new run there",
              file=sys.stderr)
        run = _recording_physics(run, values)
        return Plan(run, config, values, directory, lock, None)

    step, meta = _checkpointed(directory)
    saved = _with_new_fields(meta["config"])
    effective = values
    if by_path:
        explicit = [k for k in override_keys(overrides) if k not in ("resume", "run_dir")]
        effective = copy.deepcopy(saved)
        for key, value in flatten(values).items():
            if explicitly_set(key, explicit):
                _set(effective, key, value)
        effective["resume"], effective["run_dir"] = values["resume"], str(directory.path)
    diffs = differences(_comparable(saved), _comparable(effective), IDENTITY_KEYS)
    if not diffs:  # the same task: the same physics too
        effective["physics"] = _recorded_physics(effective["env"]["name"], effective)
        diffs = _physics_differences(directory, saved, effective, overrides)
    if diffs:
        raise UsageError(
            f"the checkpoint in {directory.checkpoints} was made with a different "
            f"configuration; refusing to resume it. Differing fields:\n  " + "\n  ".join(diffs)
            + "\nResume with the checkpoint's settings, or start a new run in another run_dir.")
    run, config = from_dict(effective)
    require_training(run, config)
    _require_budget_not_below(run, saved, meta["total_steps"], step)
    run = dataclasses.replace(run, run_dir=str(directory.path))
    return Plan(run, config, effective, directory, lock, step)

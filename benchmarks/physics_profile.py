"""Where an env step's device time goes: the kernels of each stage of MJX's physics.

For each task, `--steps` env steps of our env (`jax.vmap(env.step)` at batch `--batch`, uniform
random actions, after at least 200 warm-up steps) run `--calls` times under JAX's profiler. Every
device operation is attributed to the innermost MJX stage whose named scope its HLO
instruction carries: MJX's own scopes (`fwd_velocity`, `fwd_actuation`, `fwd_acceleration`,
`solve`, the integrator's `euler` / `rungekutta4`) and, set here for the profile only, the
stages of `fwd_position` (`kinematics`, `com_pos`, `crb`, `factor_m`, `collision`,
`make_constraint`, `transmission`); the rest (the env's reward and observation, the loop)
is `other`. Per env step: each stage's kernels and device time, the device's busy time
against the wall-clock (the rest is the launch-bound idle time between kernels).

    python -m benchmarks.physics_profile --tasks ant halfcheetah
    python -m benchmarks.physics_profile --tasks hopper --smoke    # tiny sizes: a CPU check

Writes `benchmarks/results/physics_profile.json`.
"""

import argparse
import collections
import contextlib
import json
import tempfile
import time
from typing import Iterator

import jax
from mujoco.mjx._src import collision_driver, constraint, smooth

from benchmarks.env_latency import env_rollout
from benchmarks.device_trace import counted_events, phases_of, trace_of
from benchmarks.timing import physics_record, provenance, results_path
from pgps_jax.cli.run_dir import write_atomic
from pgps_jax.envs import TASKS, make_env
from pgps_jax.envs.physics import default_platform

SCOPED_HERE = {"kinematics": smooth, "com_pos": smooth, "crb": smooth, "factor_m": smooth,
               "collision": collision_driver, "make_constraint": constraint,
               "transmission": smooth}
"""The stages of MJX's `fwd_position` (function: its module), scoped for the profile."""
STAGES = (*SCOPED_HERE, "fwd_position", "fwd_velocity", "fwd_actuation", "fwd_acceleration",
          "solve", "euler", "rungekutta4")
WARMUP = 200


@contextlib.contextmanager
def stage_scopes() -> Iterator[None]:
    """MJX's `fwd_position` stages each under a named scope of its name, while tracing."""
    originals = {name: getattr(module, name) for name, module in SCOPED_HERE.items()}

    def scoped(name, fn):
        def wrapper(*args, **kwargs):
            with jax.named_scope(name):
                return fn(*args, **kwargs)
        return wrapper
    try:
        for name, module in SCOPED_HERE.items():
            setattr(module, name, scoped(name, originals[name]))
        yield
    finally:
        for name, module in SCOPED_HERE.items():
            setattr(module, name, originals[name])


def profile_task(task: str, batch: int, steps: int, calls: int) -> dict:
    """One task's env step: per stage, kernels and device milliseconds; busy and wall ms."""
    env, key = make_env(task), jax.random.PRNGKey(0)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(key, batch))
    with stage_scopes():
        compiled = jax.jit(env_rollout(env, batch, steps)).lower(state, key).compile()
    for i in range(-(-WARMUP // steps)):  # into contact
        state = compiled(state, jax.random.fold_in(key, 1000 + i))
    jax.block_until_ready(state)
    start = time.perf_counter()
    for i in range(calls):
        jax.block_until_ready(compiled(state, jax.random.fold_in(key, i)))
    wall_ms = 1e3 * (time.perf_counter() - start) / (calls * steps)
    with tempfile.TemporaryDirectory() as log_dir:
        trace = trace_of(lambda: [compiled(state, jax.random.fold_in(key, i))
                                  for i in range(calls)], log_dir)
        events = counted_events(trace, phases_of(compiled.as_text(), STAGES),
                                default_platform())
    kernels, device_ms = collections.Counter(), collections.Counter()
    for event, _, stage in events:
        kernels[stage] += 1
        device_ms[stage] += event["dur"] / 1e3
    per_step = calls * steps
    busy = sum(device_ms.values()) / per_step
    return {"task": task, "batch": batch, "steps": steps, "calls": calls,
            "physics": physics_record(env),
            "n_frames": env.n_frames,
            "wall_ms_per_env_step": wall_ms, "device_busy_ms_per_env_step": busy,
            "device_idle_fraction": max(0.0, 1 - busy / wall_ms),
            "kernels_per_env_step": sum(kernels.values()) / per_step,
            "stages": {stage: {"kernels": kernels[stage] / per_step,
                               "device_ms": device_ms[stage] / per_step}
                       for stage in (*STAGES, "other") if kernels[stage]}}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="*", default=["ant", "halfcheetah"], choices=TASKS)
    parser.add_argument("--batch", type=int, default=60)
    parser.add_argument("--steps", type=int, default=20, help="env steps per profiled call")
    parser.add_argument("--calls", type=int, default=3)
    parser.add_argument("--out", help="default: benchmarks/results/physics_profile.json; with "
                        "--smoke, the same name in a temporary directory")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args(argv)
    for option in ("batch", "steps", "calls"):
        if getattr(args, option) < 1:
            parser.error(f"--{option} must be a positive integer, not {getattr(args, option)}")
    if args.smoke:
        args.batch, args.steps, args.calls = 2, 2, 1
    out = results_path(args.out, "benchmarks/results/physics_profile.json", args.smoke)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {**provenance(), "tasks": []}
    for task in args.tasks:
        result["tasks"].append(profile_task(task, args.batch, args.steps, args.calls))
        print(json.dumps(result["tasks"][-1]), flush=True)
        # after every task: a cut-off run keeps its part
        write_atomic(out, json.dumps(result, indent=1).encode())


if __name__ == "__main__":
    main()

"""Milliseconds per env step of each task at batch 10, 60 and 1024, in contact.

For every task and batch size: our env (`jax.vmap(env.step)` in a `lax.scan`, uniform random
actions) after 200 warm-up steps of random actions, against the bare-physics floor on the
same model and settings from the same warmed-up physics state: `n_frames` calls of
`jax.vmap(mjx.step)` in a `lax.fori_loop` per env step, same random actions. At batch 60,
Brax's own env (`brax.envs.get_environment(task, backend="mjx")`) as shipped and with our
solver settings, started from our warmed-up positions and velocities (Brax's swimmer refuses
the MJX backend). Also at batch 60, one variant of our env (`--alternative`: by default
Newton with 1 iteration, hopper's and swimmer's own and two fewer than the other tasks'),
and how closely it agrees with our env where their states have the same structure: from 20
states along our env's rollout, one step of each under the same actions, the largest
difference of the next observation relative to each env's largest |observation|
(`benchmarks.step_agreement`, which also gives the spread of float rounding alone). Every
function is compiled before any is timed; a figure is the median of 5 timed calls of 100
steps (Brax's env: 2 calls of 20 steps, it is slow). `--quick` times batch 60 alone, without
Brax's env: a quarter of the compilation, for comparing settings or XLA flags (`XLA_FLAGS`
is recorded with the results).

    python -m benchmarks.env_latency  # table on stdout, benchmarks/results/env_latency.json
    python -m benchmarks.env_latency --tasks ant --alternative fused_solve=false --out ant.json
    XLA_FLAGS=--xla_gpu_enable_command_buffer=+WHILE python -m benchmarks.env_latency --quick \
        --tasks ant --out ant_command_buffers.json
"""

import argparse
import concurrent.futures
import json
import os
import time

from brax import envs as brax_envs
import jax
import jax.numpy as jnp
from mujoco import mjx
import numpy as np

from benchmarks.step_agreement import differences, variant_name
from benchmarks.timing import physics_record
from pgps_jax.cli.assignments import env_assignments
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import TASKS, make_env

BATCHES = (10, 60, 1024)
BRAX_BATCH = 60
ALTERNATIVE = {"iterations": 1}
"""`make_env` arguments of the one variant of our env also timed at batch 60 (`--alternative`):
by default one solver iteration, what halfcheetah's, walker2d's and the ant's three cost
against the single iteration they once had."""
WARMUP, STEPS, REPEATS = 200, 100, 5
BRAX_STEPS, BRAX_REPEATS = 20, 2
BRAX_NAMES = {"halfcheetah": "halfcheetah", "hopper": "hopper", "walker2d": "walker2d",
              "ant": "ant"}


def _actions(key, n_steps, batch, action_size):
    return jax.random.uniform(key, (n_steps, batch, action_size), minval=-1.0, maxval=1.0)


def env_rollout(env, batch: int, n_steps: int):
    """(state, key) -> state after n_steps of vmap(env.step) under random actions."""
    def rollout(state, key):
        actions = _actions(key, n_steps, batch, env.action_size)
        return jax.lax.scan(lambda s, a: (jax.vmap(env.step)(s, a), None), state, actions)[0]
    return rollout


def bare_rollout(env, batch: int, n_steps: int):
    """(data, key) -> data after n_steps × n_frames of vmap(mjx.step) under random controls,
    its matrix products at the env's precision."""
    model = env.mjx_model

    def env_step(data, ctrl):
        return jax.lax.fori_loop(
            0, env.n_frames,
            lambda _, d: jax.vmap(lambda x, u: mjx.step(model, x.replace(ctrl=u)))(d, ctrl),
            data), None

    def rollout(data, key):
        with jax.default_matmul_precision(env.physics.matmul_precision):
            return jax.lax.scan(env_step, data,
                                _actions(key, n_steps, batch, env.action_size))[0]
    return rollout


def brax_env(task: str, settings_from=None):
    """Brax's env on MJX, as shipped or with the solver options of our env `settings_from`."""
    env = brax_envs.get_environment(BRAX_NAMES[task], backend="mjx")
    if settings_from is not None:
        opt = settings_from.mjx_model.opt
        env.sys = env.sys.tree_replace({
            "opt.solver": opt.solver, "opt.iterations": opt.iterations,
            "opt.ls_iterations": opt.ls_iterations, "opt.disableflags": opt.disableflags})
    return env


def compile_fn(fn, *example_args):
    """AOT-compiles fn for arguments shaped like example_args (arrays or shape structs)."""
    return jax.jit(fn).lower(*example_args).compile()


def timed(fn, state, key, repeats: int) -> float:
    """Median seconds of `repeats` calls of fn(state, key)."""
    times = []
    for i in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(state, jax.random.fold_in(key, i)))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def active_contacts(data) -> float:
    """Mean number of penetrating contacts per env."""
    return float(jnp.mean(jnp.sum(data._impl.contact.dist < 0, axis=-1)))


def build(task: str, pool: concurrent.futures.Executor, alternative: dict,
          batches: tuple[int, ...], with_brax: bool) -> dict:
    """Starts compiling, on `pool`, every function one task's measurements need."""
    env = make_env(task)
    key = jax.random.PRNGKey(0)
    jobs = {}
    for batch in batches:
        state = jax.eval_shape(jax.vmap(env.reset), jax.random.split(key, batch))
        jobs["env", batch] = (env_rollout(env, batch, STEPS), state, key)
        jobs["bare", batch] = (bare_rollout(env, batch, STEPS), state.pipeline_state, key)
    alt = make_env(task, **alternative)
    actions = jax.ShapeDtypeStruct((BRAX_BATCH, env.action_size), jnp.float32)
    shapes = {name: jax.eval_shape(jax.vmap(variant.reset), jax.random.split(key, BRAX_BATCH))
              for name, variant in (("env", env), ("alternative", alt))}
    jobs["env", "step"] = (jax.vmap(env.step), shapes["env"], actions)
    jobs["alternative", "step"] = (jax.vmap(alt.step), shapes["alternative"], actions)
    jobs["alternative"] = (env_rollout(alt, BRAX_BATCH, STEPS), shapes["alternative"], key)
    jobs["alternative", "reset"] = (jax.vmap(alt.reset), jax.random.split(key, BRAX_BATCH))
    if with_brax and task in BRAX_NAMES:
        keys = jax.random.split(key, BRAX_BATCH)
        qpos, qvel = (jax.ShapeDtypeStruct((BRAX_BATCH, n), jnp.float32)
                      for n in (env.mj_model.nq, env.mj_model.nv))
        for name, settings_from in (("brax", None), ("brax_same_settings", env)):
            benv = brax_env(task, settings_from)
            state = jax.eval_shape(jax.vmap(benv.reset), keys)
            jobs[name, "reset"] = (jax.vmap(benv.reset), keys)
            jobs[name, "init"] = (jax.vmap(benv.pipeline_init), qpos, qvel)
            jobs[name] = (env_rollout(benv, BRAX_BATCH, BRAX_STEPS), state, key)
    return {"env": env} | {k: pool.submit(compile_fn, *job) for k, job in jobs.items()}


def measure(task: str, fns: dict, alternative: dict, batches: tuple[int, ...]) -> dict:
    """Times one task's compiled functions; returns its figures (Brax's env None where it was
    not compiled)."""
    env, key = fns["env"], jax.random.PRNGKey(1)
    out = {"n_frames": env.n_frames, "dt": env.dt,
           "physics": physics_record(env)}
    for batch in batches:
        state = jax.jit(jax.vmap(env.reset))(jax.random.split(key, batch))
        for i in range(WARMUP // STEPS):
            state = fns["env", batch](state, jax.random.fold_in(key, 100 + i))
        env_s = timed(fns["env", batch], state, key, REPEATS)
        bare_s = timed(fns["bare", batch], state.pipeline_state, key, REPEATS)
        out[f"batch_{batch}"] = {
            "env_ms": 1e3 * env_s / STEPS, "bare_ms": 1e3 * bare_s / STEPS,
            "ratio": env_s / bare_s, "contacts_per_env": active_contacts(state.pipeline_state),
            "done_fraction": float(state.done.mean())}
        if batch == BRAX_BATCH:
            warm = state
    start = fns["alternative", "reset"](jax.random.split(key, BRAX_BATCH))  # its own Data
    start = start.replace(obs=warm.obs, pipeline_state=start.pipeline_state.replace(
        qpos=warm.pipeline_state.qpos, qvel=warm.pipeline_state.qvel))
    jax.block_until_ready(fns["alternative"](start, key))  # first call, untimed
    out[f"{variant_name(alternative)}_ms_batch_{BRAX_BATCH}"] = (
        1e3 * timed(fns["alternative"], start, key, REPEATS) / STEPS)
    out[f"{variant_name(alternative)}_largest_relative_difference"] = agreement(
        fns, warm, start, key)
    for name in ("brax", "brax_same_settings"):
        if (name, "reset") not in fns:
            out[f"{name}_ms_batch_{BRAX_BATCH}"] = None
            continue
        state = fns[name, "reset"](jax.random.split(key, BRAX_BATCH))
        qpos, qvel = warm.pipeline_state.qpos, warm.pipeline_state.qvel
        state = state.replace(pipeline_state=fns[name, "init"](qpos, qvel))
        state = fns[name](state, key)  # first call, untimed
        out[f"{name}_ms_batch_{BRAX_BATCH}"] = (
            1e3 * timed(fns[name], state, key, BRAX_REPEATS) / BRAX_STEPS)
    return out


def agreement(fns: dict, warm, alternative_start, key) -> float | None:
    """The largest relative difference of the next observation between our env and the
    variant, one step each from the same states along our env's rollout from `warm`
    (`step_agreement.differences`); None where the variant's state differs from ours in
    structure or shapes."""
    def layout(tree):
        return jax.tree.structure(tree), [jnp.shape(x) for x in jax.tree.leaves(tree)]
    if layout(warm) != layout(alternative_start):
        return None
    return float(differences(fns["env", "step"], fns["alternative", "step"], warm, key,
                             fns["env"].action_size).max())


def table(results: dict, alternative: dict, batches: tuple[int, ...]) -> str:
    """The results as a markdown table."""
    variant = variant_name(alternative)
    header = ["task", *(f"env ms @{b}" for b in batches), f"floor ms @{BRAX_BATCH}",
              f"ratio @{BRAX_BATCH}", f"ratio @{batches[0]} / @{batches[-1]}",
              f"Brax env ms @{BRAX_BATCH} (as shipped / our settings)",
              f"ours, {variant}, ms @{BRAX_BATCH}", f"{variant}: largest relative difference"]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for task, r in results["tasks"].items():
        b = r[f"batch_{BRAX_BATCH}"]
        brax = " / ".join("—" if r[f"{n}_ms_batch_{BRAX_BATCH}"] is None
                          else f"{r[f'{n}_ms_batch_{BRAX_BATCH}']:.2f}"
                          for n in ("brax", "brax_same_settings"))
        difference = r[f"{variant}_largest_relative_difference"]
        difference = "— (other state shapes)" if difference is None else f"{difference:.1e}"
        lines.append(
            f"| {task} | " + " | ".join(f"{r[f'batch_{x}']['env_ms']:.2f}" for x in batches)
            + f" | {b['bare_ms']:.2f} | {b['ratio']:.2f} | {r[f'batch_{batches[0]}']['ratio']:.2f}"
            f" / {r[f'batch_{batches[-1]}']['ratio']:.2f} | {brax}"
            f" | {r[f'{variant}_ms_batch_{BRAX_BATCH}']:.2f}"
            f" | {difference} |")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--out", default="benchmarks/results/env_latency.json")
    parser.add_argument("--alternative", nargs="*", metavar="NAME=VALUE",
                        default=[f"{k}={v}" for k, v in ALTERNATIVE.items()],
                        help="make_env arguments of the variant also timed at batch 60 "
                             "(e.g. unroll_solver=false)")
    parser.add_argument("--quick", action="store_true",
                        help=f"batch {BRAX_BATCH} alone, without Brax's env")
    args = parser.parse_args()
    try:
        alternative = env_assignments(args.alternative, "--alternative")
    except UsageError as e:
        parser.error(str(e))
    tasks = args.tasks.split(",")
    unknown = sorted(set(tasks) - set(TASKS))
    if unknown:
        parser.error(f"unknown task(s) {', '.join(unknown)}; choose from {', '.join(TASKS)}")
    batches = (BRAX_BATCH,) if args.quick else BATCHES
    start = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        pending = {task: build(task, pool, alternative, batches, not args.quick)
                   for task in tasks}
        compiled = {task: {k: v if k == "env" else v.result() for k, v in fns.items()}
                    for task, fns in pending.items()}
    compile_s = time.perf_counter() - start
    print(f"compiled in {compile_s:.0f} s", flush=True)
    results = {"device": jax.devices()[0].device_kind, "xla_flags": os.environ.get("XLA_FLAGS", ""),
               "compile_s": compile_s, "warmup_steps": WARMUP, "timed_steps": STEPS,
               "repeats": REPEATS, "tasks": {}}
    for task in tasks:
        results["tasks"][task] = measure(task, compiled[task], alternative, batches)
        print(task, json.dumps(results["tasks"][task]), flush=True)
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)
    print(table(results, alternative, batches))


if __name__ == "__main__":
    main()

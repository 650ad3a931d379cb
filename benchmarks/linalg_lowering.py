"""Physics per env step with MJX's small factorisations as library calls or written out.

For each task: `physics.step_frames` (an env step's `n_frames` MJX steps) vmapped over batch 40
(a population of 10 plus 30 test episodes) in a `lax.scan` of uniform random controls, from
states warmed up by 200 such steps. Variants:
- `library`: JAX's GPU lowering of `cho_factor` / `cho_solve` (batched cuSOLVER potrf,
  cuBLAS trsm), `write_out_linalg=False`;
- `written_out`: `small_linalg`'s fused versions (`write_out_linalg=True`, the GPU default);
- `sparse`: MuJoCo's sparse mass matrix with the library calls (MJX factorises it with
  gathers and scatters; the Newton Hessian still goes to cuSOLVER);
- `cg`: the CG solver with the library calls (other physics: a reference only).
Milliseconds per env step (median of 5 calls of 100 steps), compile seconds (the variants of a
task compile side by side), and the largest |Δqpos|, |Δqvel| of `written_out` against
`library` after one env step from the same states.

    python benchmarks/linalg_lowering.py [--tasks ...] [--variants ...] [--out FILE] [--smoke]
"""

import argparse
import functools
import json
import time

import jax
import mujoco
from mujoco import mjx
import numpy as np

from pgps_jax.compile_ahead import compile_ahead
from pgps_jax.envs import TASKS, make_env, physics

BATCH, WARMUP, STEPS, REPEATS = 40, 200, 100, 5
VARIANTS = ("library", "written_out", "sparse", "cg")


def scan_steps(model, n_frames, n_steps, write_out_linalg):
    """(data, key) -> data after `n_steps` env steps of random controls."""
    step = jax.vmap(functools.partial(physics.step_frames, model, n_frames=n_frames,
                                      write_out_linalg=write_out_linalg))

    def run(data, key):
        controls = jax.random.uniform(key, (n_steps, BATCH, model.nu), minval=-1, maxval=1)
        return jax.lax.scan(lambda d, u: (step(d.replace(ctrl=u)), None), data, controls)[0]
    return jax.jit(run)


def variant_model(task, variant) -> mjx.Model:
    env = make_env(task, solver="cg") if variant == "cg" else make_env(task)
    if variant == "sparse":
        env.mj_model.opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE
        return mjx.put_model(env.mj_model)
    return env.mjx_model


def task_row(task, variants, steps, repeats):
    env = make_env(task)
    data = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), BATCH)).pipeline_state
    warm = scan_steps(env.mjx_model, env.n_frames, WARMUP, False)(data, jax.random.PRNGKey(3))
    starts, programs = {}, {}
    for variant in variants:
        model = variant_model(task, variant)
        start = jax.vmap(lambda q, v: mjx.make_data(model).replace(qpos=q, qvel=v))(
            warm.qpos, warm.qvel)
        starts[variant] = start
        programs[variant] = (scan_steps(model, env.n_frames, steps, variant == "written_out"),
                             (start, jax.random.PRNGKey(1)))
        programs[variant + "/one"] = (scan_steps(model, env.n_frames, 1,
                                                 variant == "written_out"),
                                      (start, jax.random.PRNGKey(2)))
    t = time.perf_counter()
    futures = compile_ahead(programs)
    compiled, compile_s = {}, {}
    for name, future in futures.items():
        compiled[name] = future.result()
        compile_s[name] = time.perf_counter() - t
    row = {}
    for variant in variants:
        fn, start, key = compiled[variant], starts[variant], jax.random.PRNGKey(1)
        jax.block_until_ready(fn(start, key))
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(fn(start, key))
            times.append(time.perf_counter() - t)
        row[variant] = {"ms_per_step": float(np.median(times)) / steps * 1e3,
                        "compile_s_side_by_side": compile_s[variant]}
    if {"library", "written_out"} <= set(variants):
        a, b = (compiled[v + "/one"](starts[v], jax.random.PRNGKey(2))
                for v in ("library", "written_out"))
        row["written_out"]["max_abs_diff_after_one_step"] = float(max(
            np.abs(np.asarray(a.qpos) - np.asarray(b.qpos)).max(),
            np.abs(np.asarray(a.qvel) - np.asarray(b.qvel)).max()))
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=list(TASKS))
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--out", default="benchmarks/results/linalg_lowering.json")
    parser.add_argument("--smoke", action="store_true", help="a few steps: check the script")
    args = parser.parse_args()
    steps, repeats = (2, 1) if args.smoke else (STEPS, REPEATS)
    out = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
           "mujoco": mujoco.__version__, "batch": BATCH, "tasks": {}}
    for task in args.tasks:
        out["tasks"][task] = task_row(task, args.variants, steps, repeats)
        print(task, json.dumps(out["tasks"][task]), flush=True)
    json.dump(out, open(args.out, "w"), indent=1)


if __name__ == "__main__":
    main()

"""Physics per env step with MJX's small factorisations as library calls or written out,
and with its line search as a device loop or unrolled.

For each task: `physics.step_frames` (an env step's `n_frames` MJX steps) vmapped over batch 40
(a population of 10 plus 30 test episodes) in a `lax.scan` of uniform random controls, from
states warmed up by 200 such steps. Variants:
- `library`: JAX's GPU lowering of `cho_factor` / `cho_solve` (batched cuSOLVER potrf,
  cuBLAS trsm), `write_out_linalg=False`;
- `written_out`: `small_linalg`'s fused versions (`write_out_linalg=True`), one expression
  per matrix entry;
- `unrolled_search`: `written_out` with the Newton solver's line search unrolled
  (`unroll_line_search=True`; with `written_out`, the GPU default); every other variant keeps
  it a device loop;
- `written_out_columns`: the same rewrite with one vector expression per column (fewer
  operations to compile; on an H200 it compiled 16 % faster but stepped 15 % slower);
- `sparse`: MuJoCo's sparse mass matrix with the library calls (MJX factorises it with
  gathers and scatters; the Newton Hessian still goes to cuSOLVER);
- `cg`: the CG solver with the library calls (other physics: a reference only).
Milliseconds per env step (median of 5 calls of 100 steps), compile seconds (each variant
compiled on its own, one after the other), and the largest |Δqpos|, |Δqvel| of each
written-out variant against `library` after one env step from the same states.

    python benchmarks/linalg_lowering.py [--tasks ...] [--variants ...] [--out FILE] [--smoke]
"""

import argparse
import contextlib
import functools
import json
import os
import sys
import time
from unittest import mock

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx
import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from throughput import timed  # noqa: E402  (sibling benchmark)

from pgps_jax.envs import TASKS, make_env, physics, small_linalg  # noqa: E402

BATCH, WARMUP, STEPS, REPEATS = 40, 200, 100, 5
VARIANTS = ("library", "written_out", "unrolled_search", "written_out_columns", "sparse", "cg")


def cholesky_columns(a):
    """Lower Cholesky factor, one vector expression per column (NaN handling as
    `small_linalg`): L[:, j] = (A[:, j] − L[:, :j] L[j, :j]ᵀ) / L[j, j] below the diagonal."""
    n = a.shape[-1]
    rows, columns = np.arange(n), []
    positive = jnp.ones(a.shape[:-2], bool)
    for j in range(n):
        column = a[..., :, j]
        if columns:
            done = jnp.stack(columns, -1)
            column = column - jnp.sum(done * done[..., j:j + 1, :], -1)
        pivot = column[..., j]
        positive &= pivot > 0
        columns.append(jnp.where(rows >= j, column / jnp.sqrt(pivot)[..., None], 0.0))
    lower = jnp.stack(columns, -1)
    return jnp.where(positive[..., None, None] | ~np.tri(n, dtype=bool), lower, jnp.nan)


def triangular_solve_columns(a, b, *, left_side, lower, transpose_a, conjugate_a,
                             unit_diagonal):
    """`small_linalg.triangular_solve` by columns: each solved row x_i is removed from the rows
    still to solve, B ← B − op(A)[:, i] x_i, one vector expression per row."""
    if not left_side:
        solution = triangular_solve_columns(a, jnp.swapaxes(b, -1, -2), left_side=True,
                                            lower=lower, transpose_a=not transpose_a,
                                            conjugate_a=conjugate_a, unit_diagonal=unit_diagonal)
        return jnp.swapaxes(solution, -1, -2)
    n = a.shape[-1]
    order = list(range(n)) if lower != transpose_a else list(range(n - 1, -1, -1))
    residual, solution = b, [None] * n
    for step, i in enumerate(order):
        row = residual[..., i, :]
        solution[i] = row if unit_diagonal else row / a[..., i, i, None]
        to_solve = np.isin(np.arange(n), order[step + 1:])
        if to_solve.any():
            column = jnp.where(to_solve, a[..., i, :] if transpose_a else a[..., :, i], 0.0)
            residual = residual - column[..., :, None] * solution[i][..., None, :]
    return jnp.stack(solution, -2)


def forms(variant):
    """Context in which `small_linalg` writes out `variant`'s forms."""
    if variant != "written_out_columns":
        return contextlib.nullcontext()
    return mock.patch.dict(small_linalg._WRITTEN_OUT, {
        jax.lax.linalg.cholesky_p: cholesky_columns,
        jax.lax.linalg.triangular_solve_p: triangular_solve_columns})


def scan_steps(model, n_frames, n_steps, variant):
    """(data, key) -> data after `n_steps` env steps of random controls."""
    step = jax.vmap(functools.partial(
        physics.step_frames, model, n_frames=n_frames,
        write_out_linalg=variant.startswith("written_out") or variant == "unrolled_search",
        unroll_line_search=variant == "unrolled_search"))

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
    warm = scan_steps(env.mjx_model, env.n_frames, WARMUP, "library")(data,
                                                                       jax.random.PRNGKey(3))
    starts, compiled, compile_s, one_step = {}, {}, {}, {}
    for variant in variants:
        model = variant_model(task, variant)
        start = jax.vmap(lambda q, v: mjx.make_data(model).replace(qpos=q, qvel=v))(
            warm.qpos, warm.qvel)
        starts[variant] = start
        with forms(variant):
            t = time.perf_counter()
            compiled[variant] = scan_steps(model, env.n_frames, steps, variant).lower(
                start, jax.random.PRNGKey(1)).compile()
            compile_s[variant] = time.perf_counter() - t
            one_step[variant] = scan_steps(model, env.n_frames, 1, variant).lower(
                start, jax.random.PRNGKey(2)).compile()
    row = {}
    for variant in variants:
        _, seconds = timed(compiled[variant], starts[variant], jax.random.PRNGKey(1),
                           repeats=repeats)
        row[variant] = {"ms_per_step": seconds / steps * 1e3, "compile_s": compile_s[variant]}
    if "library" in variants:
        reference = one_step["library"](starts["library"], jax.random.PRNGKey(2))
        for variant in (v for v in variants if v not in ("library", "sparse", "cg")):
            result = one_step[variant](starts[variant], jax.random.PRNGKey(2))
            row[variant]["max_abs_diff_after_one_step"] = float(max(
                np.abs(np.asarray(reference.qpos) - np.asarray(result.qpos)).max(),
                np.abs(np.asarray(reference.qvel) - np.asarray(result.qvel)).max()))
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

"""Rewrites of MJX's physics step that make it faster on a GPU, each behind a `Physics` switch.

- `small_linalg`: the mass-matrix and Newton-Hessian Cholesky factorisations and triangular
  solves of up to `small_linalg.MAX_SIZE` rows as fused array code instead of batched
  cuSOLVER / cuBLAS calls (`Physics.write_out_linalg`).
- `line_search`: the Newton solver's line search without a device loop
  (`Physics.unroll_line_search`).
- `solver_loop`: the solver's iterations, when there are several, without a device loop
  (`Physics.unroll_solver`).
- `fused_solve`: the whole constraint solve as one kernel per env (`Physics.fused_solve`;
  with it the two rules above have nothing left to rewrite and are not applied).

All default to on for a GPU (the written-out linear algebra for models of up to
`small_linalg.MAX_SIZE` degrees of freedom; the fused solve for the models it covers, with
float32 products, which on the five tasks leaves the two loop rules idle) and off for a CPU,
where the library calls are faster and a loop's trip costs no pause for the host. Measured
before the fused solve, on an H200, halfcheetah's physics at
batch 40 takes 1.05 ms per env step with the first two instead of 1.33, and the ant's env step
(2 solver iterations) at batch 60 7.56 ms with its iterations written out instead of 10.69
(BENCHMARKS.md). They re-trace `mjx.step` (`rewrite`) and match its code by primitive, shape
and parameter names, as mujoco-mjx 3.17.0 and JAX 0.10.2 trace it; where a later version no
longer fits a rule, MJX's own code runs and one warning says which rule.
"""

from typing import Callable

from mujoco import mjx

from pgps_jax.envs.mjx_rewrites import fused_solve as fused
from pgps_jax.envs.mjx_rewrites.line_search import unrolled_line_search
from pgps_jax.envs.mjx_rewrites.rewrite import rewrite
from pgps_jax.envs.mjx_rewrites.small_linalg import SMALL_LINALG
from pgps_jax.envs.mjx_rewrites.solver_loop import unrolled_solver

def physics_step(model: mjx.Model, write_out_linalg: bool, unroll_line_search: bool,
                 unroll_solver: bool, fused_solve: bool,
                 on_gpu: bool) -> Callable[[mjx.Data], mjx.Data]:
    """`mjx.step` of `model`, with the rewrites that are switched on (the fused solve's kernel
    interpreted unless `on_gpu`). ValueError if the fused solve does not cover `model`."""
    rules = []
    if write_out_linalg:
        rules.append(SMALL_LINALG)
    if fused_solve:
        fused.refuse_unsupported(model)
    else:
        if unroll_line_search:
            rules.append(unrolled_line_search(int(model.opt.ls_iterations)))
        if unroll_solver and model.opt.iterations > 1:
            rules.append(unrolled_solver(int(model.opt.iterations),
                                         int(model.opt.ls_iterations)))

    def step(data: mjx.Data) -> mjx.Data:
        if not fused_solve:
            return mjx.step(model, data)
        with fused.solve_replaced(interpret=not on_gpu):
            return mjx.step(model, data)

    return rewrite(step, rules) if rules else step

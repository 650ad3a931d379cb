"""MJX's Newton constraint solve as one kernel per env (`Physics.fused_solve`).

On a GPU MJX's solve is a chain of small kernels, about 105 per solve for the ant (three
iterations of two line-search steps: half of the device time of its env step, BENCHMARKS.md
"Where the ant's step goes on the GPU"), each a few microseconds whatever the batch. `solve`
computes the same thing for each env as one Pallas (Triton) program over zero-padded tiles:
the warm start's choice, the Gauss and constraint costs, the Hessian M + Jᵀ·diag(D·active)·J
and its Cholesky factor (its own, in masked tile updates), MJX's bracketing line search and
stopping tests, so that its results agree with MJX's to float tolerance. It covers Newton's
method with pyramidal cones and no friction loss (`refuse_unsupported`); off a GPU the program
runs interpreted, for the tests. On an H100 it makes the env step 1.2-1.9 times shorter, its
next states within float32's rounding of MJX's step with float32 products (BENCHMARKS.md "The
Newton solve as one kernel"); `Physics` uses it by default on a GPU.

`solve_replaced()` makes `mjx.step` call `solve` while it is traced in the calling thread.
"""

import contextlib
import functools
import threading
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import mujoco
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pallas_triton
from mujoco import mjx
from mujoco.mjx._src import solver as mjx_solver
from mujoco.mjx._src import support
import numpy as np

_WARMSTART_OFF = int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)


def _unsupported(model: mjx.Model) -> Optional[str]:
    """Why `solve` cannot stand in for MJX's on `model`, or None."""
    if model.opt.solver != mujoco.mjtSolver.mjSOL_NEWTON:
        return "the solver is not Newton's"
    if model.opt.cone != mujoco.mjtCone.mjCONE_PYRAMIDAL:
        return "the friction cones are not pyramidal"
    if model._impl.dof_hasfrictionloss.any() or model._impl.tendon_hasfrictionloss.any():
        return "the model has friction loss"
    return None


def covers(model: mjx.Model) -> bool:
    """Whether `solve` can stand in for MJX's on `model`."""
    return _unsupported(model) is None


def refuse_unsupported(model: mjx.Model) -> None:
    """ValueError naming why `solve` cannot stand in for MJX's on `model`, if it cannot."""
    reason = _unsupported(model)
    if reason:
        raise ValueError(f"fused_solve covers Newton's method with pyramidal cones and no "
                         f"friction loss; here {reason}: set fused_solve=false")


def _padded(n: int) -> int:
    """The tile length for `n` rows: a power of two, at least 16 (Triton's matrix product)."""
    return max(16, 1 << (max(n, 1) - 1).bit_length())


def _cholesky_solve(h: jax.Array, g: jax.Array) -> jax.Array:
    """x with h x = g, h symmetric positive definite: its Cholesky factor and two triangular
    solves written as masked tile updates (a program cannot index its registers)."""
    size = h.shape[0]
    rows = jax.lax.broadcasted_iota(jnp.int32, (size, size), 0)
    cols = jax.lax.broadcasted_iota(jnp.int32, (size, size), 1)
    idx = jax.lax.broadcasted_iota(jnp.int32, (size,), 0)
    entry = lambda v, i: jnp.sum(jnp.where(idx == i, v, 0.0))

    def factor(j, carry):
        rest, lower = carry
        col = jnp.sum(jnp.where(cols == j, rest, 0.0), axis=1)
        pivot = jnp.sqrt(entry(col, j))
        column = jnp.where(idx > j, col / pivot, jnp.where(idx == j, pivot, 0.0))
        below = jnp.where(idx > j, column, 0.0)
        return (rest - below[:, None] * below[None, :],
                jnp.where(cols == j, column[:, None], lower))

    _, lower = jax.lax.fori_loop(0, size, factor, (h, jnp.zeros_like(h)))

    def forward(i, y):  # lower · y = g
        row = jnp.sum(jnp.where(rows == i, lower, 0.0), axis=0)
        partial = jnp.sum(jnp.where(idx < i, row * y, 0.0))
        return jnp.where(idx == i, (entry(g, i) - partial) / entry(row, i), y)

    y = jax.lax.fori_loop(0, size, forward, jnp.zeros_like(g))

    def backward(k, x):  # lowerᵀ · x = y
        i = size - 1 - k
        col = jnp.sum(jnp.where(cols == i, lower, 0.0), axis=1)
        partial = jnp.sum(jnp.where(idx > i, col * x, 0.0))
        return jnp.where(idx == i, (entry(y, i) - partial) / entry(col, i), x)

    return jax.lax.fori_loop(0, size, backward, jnp.zeros_like(g))


class _Iterate(NamedTuple):
    """What one iteration of MJX's solver loop carries to the next (its `Context`)."""
    qacc: jax.Array
    jaref: jax.Array
    ma: jax.Array
    search: jax.Array
    gauss: jax.Array
    cost: jax.Array
    prev_cost: jax.Array
    grad: jax.Array
    efc_force: jax.Array
    qfrc_constraint: jax.Array


def solve_tiles(jac, efc_d, aref, always, mass, qfrc_smooth, qacc_smooth, qacc_warm, *, nv,
                iterations, ls_iterations, tolerance, ls_tolerance, warmstart):
    """(qacc, qfrc_constraint, efc_force) of MJX's `solver.solve` for one env, from its
    constraint rows (`jac` [E, V], `efc_d`, `aref`; `always`: the equality and friction rows)
    and dofs (`mass` [V, V], the full mass matrix; the smooth force and acceleration, the
    warm start), zero-padded to E rows and V dofs with `mass`'s padded diagonal 1."""
    size = mass.shape[0]
    rows = jax.lax.broadcasted_iota(jnp.int32, (size, size), 0)
    cols = jax.lax.broadcasted_iota(jnp.int32, (size, size), 1)
    trace = jnp.maximum(mujoco.mjMINVAL,
                        jnp.sum(jnp.where((rows == cols) & (rows < nv), mass, 0.0)))
    dot = lambda a, b: jnp.sum(a * b)
    # MJX's math.norm: 0 where every component is within 1e-8 of it (jnp.allclose)
    norm = lambda v: jnp.where(jnp.max(jnp.abs(v)) <= 1e-8, 0.0, jnp.sqrt(dot(v, v)))
    mul_m = lambda v: jnp.sum(mass * v[None, :], axis=1)
    mul_j = lambda v: jnp.sum(jac * v[None, :], axis=1)

    def constraint(qacc, jaref, ma):  # MJX's _update_constraint
        active = (jaref < 0) | always
        force = efc_d * -jaref * active
        cost = 0.5 * jnp.sum(efc_d * jaref * jaref * active)
        gauss = 0.5 * dot(ma - qfrc_smooth, qacc - qacc_smooth)
        return active, force, cost + gauss, gauss, jnp.sum(jac * force[:, None], axis=0)

    def gradient(ma, qfrc_constraint, active):  # MJX's _update_gradient
        grad = ma - qfrc_smooth - qfrc_constraint
        weighted = jac * (efc_d * active)[:, None]
        hessian = mass + jnp.dot(weighted.T, jac, precision=jax.lax.Precision.HIGHEST)
        return grad, _cholesky_solve((hessian + hessian.T) * 0.5, grad)

    def point(alpha, jaref, jv, quads, gauss_quad):  # MJX's _LSPoint.create
        active = (jaref + alpha * jv < 0) | always
        q0, q1, q2 = (g + jnp.sum(q * active) for g, q in zip(gauss_quad, quads))
        return (alpha, alpha * alpha * q2 + alpha * q1 + q0, 2 * alpha * q2 + q1,
                2 * q2 + (q2 == 0) * mujoco.mjMINVAL)

    def line_search(qacc, jaref, ma, search, gauss):  # MJX's _linesearch
        gtol = tolerance * ls_tolerance * norm(search) * trace
        mv, jv = mul_m(search), mul_j(search)
        gauss_quad = (gauss, dot(search, ma) - dot(search, qfrc_smooth), 0.5 * dot(search, mv))
        quads = (0.5 * jaref * jaref * efc_d, jv * jaref * efc_d, 0.5 * jv * jv * efc_d)
        at = lambda alpha: point(alpha, jaref, jv, quads, gauss_quad)
        pick = lambda c, x, y: tuple(jnp.where(c, a, b) for a, b in zip(x, y))
        newton = lambda p: at(p[0] - p[2] / p[3])
        p0 = at(jnp.zeros((), jnp.float32))
        rows_0 = jnp.maximum(p0[1] - gauss_quad[0], 0.0)
        rows_2 = jnp.maximum(0.5 * p0[3] - gauss_quad[2], 0.0)
        dmag = 2.0 * jnp.sqrt(rows_0 * rows_2) + jnp.abs(gauss_quad[1])
        gtol_accept = jnp.maximum(gtol, 8 * np.finfo(np.float32).eps * dmag)
        converged = lambda p: (jnp.abs(p[2]) < gtol_accept) & (p[1] < p0[1])
        in_bracket = lambda x, y: ((x < y) & (y < 0)) | ((x > y) & (y > 0))
        lo = newton(p0)
        lesser = lo[2] < p0[2]
        hi, lo = pick(lesser, p0, lo), pick(lesser, lo, p0)
        going = ~converged(lo) & ~converged(hi)
        for _ in range(ls_iterations):
            lo_next, hi_next, mid = newton(lo), newton(hi), at(0.5 * (lo[0] + hi[0]))
            s1 = in_bracket(lo[2], lo_next[2])
            new_lo = pick(s1, lo_next, lo)
            s2 = in_bracket(new_lo[2], mid[2])
            new_lo = pick(s2, mid, new_lo)
            s3 = in_bracket(new_lo[2], hi_next[2])
            new_lo = pick(s3, hi_next, new_lo)
            s4 = in_bracket(hi[2], hi_next[2]) | ((hi[2] < 0) & (hi_next[2] > 0))
            new_hi = pick(s4, hi_next, hi)
            s5 = in_bracket(new_hi[2], mid[2])
            new_hi = pick(s5, mid, new_hi)
            s6 = in_bracket(new_hi[2], lo_next[2])
            new_hi = pick(s6, lo_next, new_hi)
            # the lowest-cost converged candidate, the first of equals (MJX's argmin)
            c = [jnp.where(converged(p), p[1], jnp.inf) for p in (lo_next, hi_next, mid)]
            first = (c[0] <= c[1]) & (c[0] <= c[2])
            best = pick(first, lo_next, pick(c[1] <= c[2], hi_next, mid))
            done = converged(lo_next) | converged(hi_next) | converged(mid)
            new_lo, new_hi = pick(done, best, new_lo), pick(done, best, new_hi)
            swapped = (s1 | s2 | s3 | s4 | s5 | s6) & ~done
            lo, hi = pick(going, new_lo, lo), pick(going, new_hi, hi)
            going = going & swapped & ~converged(lo) & ~converged(hi)
        improved = (lo[1] < p0[1]) | (hi[1] < p0[1])
        alpha = jnp.where(lo[1] < hi[1], lo[0], hi[0])
        return (qacc + improved * search * alpha, jaref + improved * jv * alpha,
                ma + improved * mv * alpha)

    def iteration(it: _Iterate) -> _Iterate:  # the body of MJX's solver loop
        qacc, jaref, ma = line_search(it.qacc, it.jaref, it.ma, it.search, it.gauss)
        active, force, cost, gauss, qfrc_constraint = constraint(qacc, jaref, ma)
        grad, mgrad = gradient(ma, qfrc_constraint, active)
        return _Iterate(qacc, jaref, ma, -mgrad, gauss, cost, it.cost, grad, force,
                        qfrc_constraint)

    qacc = qacc_smooth
    if warmstart:
        cost_of = lambda q: constraint(q, mul_j(q) - aref, mul_m(q))[2]
        qacc = jnp.where(cost_of(qacc_warm) < cost_of(qacc_smooth), qacc_warm, qacc_smooth)
    jaref, ma = mul_j(qacc) - aref, mul_m(qacc)
    active, force, cost, gauss, qfrc_constraint = constraint(qacc, jaref, ma)
    grad, mgrad = gradient(ma, qfrc_constraint, active)
    it = _Iterate(qacc, jaref, ma, -mgrad, gauss, cost, jnp.inf, grad, force, qfrc_constraint)
    if iterations == 1:
        it = iteration(it)
    else:
        going = None
        for _ in range(iterations):
            improvement = (it.prev_cost - it.cost) / trace
            steep = norm(it.grad) / trace
            more = ~((improvement < tolerance) | (steep < tolerance))
            going = more if going is None else going & more
            it = _Iterate(*(jnp.where(going, new, old) for new, old in zip(iteration(it), it)))
    return it.qacc, it.qfrc_constraint, it.efc_force


def solve(m: mjx.Model, d: mjx.Data, interpret: bool) -> mjx.Data:
    """`d` with MJX's `solver.solve` applied, computed by one `solve_tiles` program per env
    (interpreted where `interpret`)."""
    impl = d._impl
    nefc, nv = impl.efc_J.shape
    rows, dofs = _padded(nefc), _padded(nv)
    pad = lambda x, n: jnp.zeros((n,), jnp.float32).at[:x.shape[0]].set(x)
    jac = jnp.zeros((rows, dofs), jnp.float32).at[:nefc, :nv].set(impl.efc_J)
    mass = jnp.eye(dofs, dtype=jnp.float32).at[:nv, :nv].set(support.full_m(m, d))
    always = (jnp.arange(rows) < impl.ne + impl.nf).astype(jnp.float32)
    settings = dict(nv=nv, iterations=int(m.opt.iterations),
                    ls_iterations=int(m.opt.ls_iterations), tolerance=float(m.opt.tolerance),
                    ls_tolerance=float(m.opt.ls_tolerance),
                    warmstart=not int(m.opt.disableflags) & _WARMSTART_OFF)

    def kernel(jac_ref, d_ref, aref_ref, always_ref, mass_ref, smooth_ref, acc_ref, warm_ref,
               qacc_ref, qfrc_ref, force_ref):
        qacc_ref[...], qfrc_ref[...], force_ref[...] = solve_tiles(
            jac_ref[...], d_ref[...], aref_ref[...], always_ref[...] > 0, mass_ref[...],
            smooth_ref[...], acc_ref[...], warm_ref[...], **settings)

    out_shape = (jax.ShapeDtypeStruct((dofs,), jnp.float32),
                 jax.ShapeDtypeStruct((dofs,), jnp.float32),
                 jax.ShapeDtypeStruct((rows,), jnp.float32))
    qacc, qfrc_constraint, efc_force = pl.pallas_call(
        kernel, out_shape=out_shape, interpret=interpret, name="fused_solve",
        compiler_params=None if interpret else pallas_triton.CompilerParams(num_warps=4),
    )(jac, pad(impl.efc_D, rows), pad(impl.efc_aref, rows), always, mass,
      pad(d.qfrc_smooth, dofs), pad(d.qacc_smooth, dofs), pad(d.qacc_warmstart, dofs))
    return d.tree_replace({"qacc": qacc[:nv], "qfrc_constraint": qfrc_constraint[:nv],
                           "_impl.efc_force": efc_force[:nefc]})


_replacing = threading.local()
"""Per thread: whether `solve_replaced` is open in it, and whether interpreted."""


def _solve_of_this_thread(original):
    """MJX's solve, or `solve` in a thread where `solve_replaced` is open: installed once in
    place of MJX's, so that threads tracing at once each get their own."""
    @functools.wraps(original)  # MJX names the solve's scope after the function
    def dispatch(m: mjx.Model, d: mjx.Data) -> mjx.Data:
        interpret = getattr(_replacing, "interpret", None)
        return original(m, d) if interpret is None else solve(m, d, interpret)

    dispatch.mjx_solve = original
    return dispatch


_install_lock = threading.Lock()


@contextlib.contextmanager
def solve_replaced(interpret: bool):
    """While open, MJX's forward dynamics traced in this thread call `solve` in place of
    `solver.solve` (the library looks its solver up when traced): trace `mjx.step` inside
    it. Other threads keep MJX's solve."""
    with _install_lock:
        if not hasattr(mjx_solver.solve, "mjx_solve"):
            mjx_solver.solve = _solve_of_this_thread(mjx_solver.solve)
    outer = getattr(_replacing, "interpret", None)
    _replacing.interpret = interpret
    try:
        yield
    finally:
        _replacing.interpret = outer

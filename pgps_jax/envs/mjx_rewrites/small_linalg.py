"""Cholesky factorisations and triangular solves of small matrices as plain array code.

MJX factorises the nv×nv mass matrix and the Newton solver's Hessian in every physics step
(nv = 5–14 here). On a GPU `jax.scipy.linalg.cho_factor` / `cho_solve` become batched cuSOLVER
and cuBLAS calls: each launches its own kernels, with pointer-array setup, outside XLA's fused
code. Written out entry by entry, the same arithmetic is a few element-wise kernels over the
batch that XLA fuses with its neighbours.

`SMALL_LINALG`, a rule of `rewrite`, replaces each Cholesky and triangular-solve primitive
on matrices up to `MAX_SIZE` rows, in the traced function and in the loops and jitted
functions it calls, by these versions; everything else is bound as traced.
"""

import jax
import jax.numpy as jnp
from jax.lax import linalg
import numpy as np

from pgps_jax.envs.mjx_rewrites.rewrite import Rule

MAX_SIZE = 10
"""Largest matrix written out. On an H200 (BENCHMARKS.md, "Small factorisations") the
written-out versions take 11–24 % off an env step for nv = 5–9 (swimmer, hopper, halfcheetah, walker2d);
at ant's nv = 14 they gain nothing and compile 2.7× longer, so ant keeps the library calls."""


def cholesky(a: jax.Array) -> jax.Array:
    """Lower Cholesky factor L, A = L Lᵀ, of a batch [..., n, n] of symmetric matrices.

    Reads the lower triangle, like LAPACK's potrf. As with JAX's `cholesky`, a matrix that is
    not positive definite (a pivot ≤ 0 or non-finite) gives NaNs in the lower triangle.
    """
    n = a.shape[-1]
    entry = [[a[..., i, j] for j in range(n)] for i in range(n)]
    factor = [[None] * n for _ in range(n)]
    positive = jnp.ones(a.shape[:-2], bool)
    for j in range(n):
        squares = sum((factor[j][k] ** 2 for k in range(j)), jnp.zeros_like(entry[j][j]))
        pivot = entry[j][j] - squares
        positive &= pivot > 0
        diagonal = jnp.sqrt(pivot)
        factor[j][j] = diagonal
        for i in range(j + 1, n):
            dot = sum((factor[i][k] * factor[j][k] for k in range(j)), jnp.zeros_like(diagonal))
            factor[i][j] = (entry[i][j] - dot) / diagonal
    zero = jnp.zeros_like(entry[0][0])
    rows = [jnp.stack([factor[i][j] if j <= i else zero for j in range(n)], -1)
            for i in range(n)]
    lower = jnp.stack(rows, -2)
    return jnp.where(positive[..., None, None] | ~np.tri(n, dtype=bool), lower, jnp.nan)


def triangular_solve(a: jax.Array, b: jax.Array, *, left_side: bool, lower: bool,
                     transpose_a: bool, conjugate_a: bool, unit_diagonal: bool) -> jax.Array:
    """X with op(A) X = B (`left_side`) or X op(A) = B, for triangular A [..., n, n].

    op(A) = Aᵀ when `transpose_a`; the arguments are those of `jax.lax.linalg.triangular_solve`
    (real matrices: `conjugate_a` changes nothing).
    """
    del conjugate_a
    if not left_side:
        # X op(A) = B  ⇔  op(A)ᵀ Xᵀ = Bᵀ.
        solution = triangular_solve(a, jnp.swapaxes(b, -1, -2), left_side=True, lower=lower,
                                    transpose_a=not transpose_a, conjugate_a=False,
                                    unit_diagonal=unit_diagonal)
        return jnp.swapaxes(solution, -1, -2)
    n = a.shape[-1]
    # The effective matrix M = op(A) is lower triangular iff lower != transpose_a.
    m = (lambda i, j: a[..., j, i]) if transpose_a else (lambda i, j: a[..., i, j])
    order = range(n) if lower != transpose_a else range(n - 1, -1, -1)
    rows = [b[..., i, :] for i in range(n)]
    solution = [None] * n
    done = []
    for i in order:
        residual = rows[i] - sum((m(i, j)[..., None] * solution[j] for j in done),
                                 jnp.zeros_like(rows[i]))
        solution[i] = residual if unit_diagonal else residual / m(i, i)[..., None]
        done.append(i)
    return jnp.stack(solution, -2)


_WRITTEN_OUT = {linalg.cholesky_p: cholesky, linalg.triangular_solve_p: triangular_solve}


def _is_small(eqn) -> bool:
    return (eqn.primitive in _WRITTEN_OUT and eqn.invars[0].aval.shape[-1] <= MAX_SIZE
            and not jnp.issubdtype(eqn.invars[0].aval.dtype, jnp.complexfloating))


SMALL_LINALG = Rule(name="small_linalg", applies=_is_small,
                    compute=lambda eqn, inputs, params: [
                        _WRITTEN_OUT[eqn.primitive](*inputs, **eqn.params)])
"""Cholesky and triangular-solve calls on matrices up to `MAX_SIZE` rows, written out."""

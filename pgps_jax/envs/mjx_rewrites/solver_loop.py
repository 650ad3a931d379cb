"""MJX's constraint-solver iterations written out: the same arithmetic without a device loop.

With more than one iteration MJX runs the solver as a `lax.while_loop` that ends after
`iterations` trips or once converged. Under `vmap` every trip runs the body for the whole
batch and keeps the converged rows as they were; on a GPU every trip also pauses while the
host reads the loop's condition (under RK4 the ant solves four times per physics step, twenty
times per env step). `unrolled_solver(iterations, ls_iterations)` writes out exactly
`iterations` trips, each kept only where the loop's own condition holds: the rows see the
same sequence of solver updates as in the loop. That holds because MJX's condition ends the
loop after `iterations` trips (`solver_niter >= iterations`); the rule applies only to loops
whose condition compares with that number.
"""

import functools

from jax.extend import core
from jax.extend.core import primitives
import jax.numpy as jnp

from pgps_jax.envs.mjx_rewrites.rewrite import Rule


def _holds_line_search(jaxpr: core.Jaxpr, ls_iterations: int) -> bool:
    """Whether `jaxpr` (or a sub-jaxpr of it) scans `ls_iterations` steps: MJX's line search."""
    return any((eqn.primitive is primitives.scan_p and eqn.params["length"] == ls_iterations)
               or any(_holds_line_search(sub, ls_iterations)
                      for sub in core.jaxprs_in_params(eqn.params))
               for eqn in jaxpr.eqns)


def _compares_with(jaxpr: core.Jaxpr, bound: int) -> bool:
    """Whether `jaxpr` compares a value with the literal `bound` (the loop's trip limit)."""
    comparisons = (primitives.lt_p, primitives.le_p, primitives.ge_p, primitives.gt_p)
    return any(eqn.primitive in comparisons
               and any(isinstance(v, core.Literal) and v.val == bound for v in eqn.invars)
               for eqn in jaxpr.eqns)


@functools.cache
def unrolled_solver(iterations: int, ls_iterations: int) -> Rule:
    """The rule that writes out the while loops whose body holds the line search (the
    solver's) as `iterations` guarded trips; one object per pair, as `rewrite` caches by
    rule."""
    def applies(eqn) -> bool:
        return (eqn.primitive is primitives.while_p
                and _compares_with(eqn.params["cond_jaxpr"].jaxpr, iterations)
                and _holds_line_search(eqn.params["body_jaxpr"].jaxpr, ls_iterations))

    def compute(eqn, inputs, params):
        n_cond, n_body = params["cond_nconsts"], params["body_nconsts"]
        cond_consts, body_consts = inputs[:n_cond], inputs[n_cond:n_cond + n_body]
        carry = list(inputs[n_cond + n_body:])
        cond = core.jaxpr_as_fun(params["cond_jaxpr"])
        body = core.jaxpr_as_fun(params["body_jaxpr"])
        for _ in range(iterations):
            (go,) = cond(*cond_consts, *carry)
            updated = body(*body_consts, *carry)
            carry = [jnp.where(go, new, old) for new, old in zip(updated, carry)]
        return carry

    return Rule(name="unrolled_solver", applies=applies, compute=compute)

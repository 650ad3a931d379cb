"""MJX's Newton line search written out: the same arithmetic without a device loop.

MJX runs the line search as a `lax.scan` of `ls_iterations` steps, each skipped by a
`lax.cond` once converged; under `vmap` every step runs anyway, and on a GPU each trip of the
loop copies its carry and pauses. `unrolled_line_search(n)` writes out every scan of exactly
n steps in the physics step (in MJX 3.17 the line search is the only one).
"""

import functools

from jax.extend.core import primitives

from pgps_jax.envs.mjx_rewrites.rewrite import Rule


@functools.cache
def unrolled_line_search(ls_iterations: int) -> Rule:
    """The rule that unrolls scans of `ls_iterations` steps (the model's line search); one
    object per length, so that `rewrite`'s cache of which sub-jaxprs hold a target serves
    every trace of the step."""
    def applies(eqn) -> bool:
        return (eqn.primitive is primitives.scan_p and eqn.params["length"] == ls_iterations
                and eqn.params["unroll"] != ls_iterations)

    return Rule(name="unrolled_line_search", applies=applies,
                compute=lambda eqn, inputs, params: primitives.scan_p.bind(
                    *inputs, **{**params, "unroll": params["length"]}))

"""A function re-traced with some of its primitive calls replaced (rewrites of MJX's step).

`rewrite(fn, rules)` traces `fn` to a jaxpr and evaluates that jaxpr again, equation by
equation, in the caller's trace (so under `vmap` the replacements are batched like the
rest). An equation that a `Rule` applies to is computed by the rule; every other one is bound
as traced. Rules reach into the closed sub-jaxprs of loops, conditionals and jitted calls
that hold an equation they apply to; the others are left as they are.
"""

import dataclasses
import functools
from typing import Callable, Sequence

import jax
from jax.extend import core


@dataclasses.dataclass(frozen=True)
class Rule:
    """What to compute in place of the equations it applies to."""

    applies: Callable[[core.JaxprEqn], bool]
    """Whether the rule computes this equation."""
    compute: Callable[..., list]
    """(eqn, inputs, params) -> the equation's outputs; `params` are the equation's own with
    their sub-jaxprs already rewritten."""


def rewrite(fn: Callable, rules: Sequence[Rule]) -> Callable:
    """`fn` (arrays -> arrays) with the equations that `rules` apply to replaced.

    Non-array inputs must be closed over (MJX's model, whose numpy fields drive tracing).
    """
    rules = tuple(rules)

    @functools.wraps(fn)
    def rewritten(*args):
        closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*args)
        outputs = _evaluate(closed.jaxpr, closed.consts, jax.tree.leaves(args), rules)
        return jax.tree.unflatten(jax.tree.structure(out_shape), outputs)

    return rewritten


def _rule_for(eqn, rules: tuple[Rule, ...]) -> Rule | None:
    return next((rule for rule in rules if rule.applies(eqn)), None)


@functools.lru_cache(maxsize=4096)
def _has_target(jaxpr: core.Jaxpr, rules: tuple[Rule, ...]) -> bool:
    return any(_rule_for(eqn, rules) is not None
               or any(_has_target(sub, rules) for sub in core.jaxprs_in_params(eqn.params))
               for eqn in jaxpr.eqns)


def _rewrite_closed(closed: core.ClosedJaxpr, rules: tuple[Rule, ...]) -> core.ClosedJaxpr:
    """`closed` re-traced with its targets replaced (unchanged if it has none)."""
    if not _has_target(closed.jaxpr, rules):
        return closed
    avals = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
             for a in closed.in_avals]
    return jax.make_jaxpr(lambda *xs: _evaluate(closed.jaxpr, closed.consts, xs, rules))(*avals)


def _rewrite_param(value, rules: tuple[Rule, ...]):
    if isinstance(value, core.ClosedJaxpr):
        return _rewrite_closed(value, rules)
    if isinstance(value, tuple) and value and all(isinstance(v, core.ClosedJaxpr) for v in value):
        return tuple(_rewrite_closed(v, rules) for v in value)
    if isinstance(value, core.Jaxpr) and _has_target(value, rules):
        raise NotImplementedError("an open sub-jaxpr holds an equation to rewrite")
    return value


def _evaluate(jaxpr: core.Jaxpr, consts, args, rules: tuple[Rule, ...]) -> list:
    """Evaluates `jaxpr` on `args`, applying `rules` and rewriting sub-jaxprs that need it."""
    values = dict(zip(jaxpr.constvars, consts))
    values.update(zip(jaxpr.invars, args))

    def read(var):
        return var.val if isinstance(var, core.Literal) else values[var]

    for eqn in jaxpr.eqns:
        inputs = [read(v) for v in eqn.invars]
        params = {k: _rewrite_param(v, rules) for k, v in eqn.params.items()}
        rule = _rule_for(eqn, rules)
        with eqn.ctx.manager:
            if rule is not None:
                outputs = rule.compute(eqn, inputs, params)
            else:
                outputs = eqn.primitive.bind(*inputs, **eqn.primitive.get_bind_params(params))
                if not eqn.primitive.multiple_results:
                    outputs = [outputs]
        values.update(zip(eqn.outvars, outputs))
    return [read(v) for v in jaxpr.outvars]

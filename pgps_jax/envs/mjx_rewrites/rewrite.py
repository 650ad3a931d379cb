"""A function re-traced with some of its primitive calls replaced (rewrites of MJX's step).

`rewrite(fn, rules)` traces `fn` to a jaxpr and evaluates that jaxpr again, equation by
equation, in the caller's trace (so under `vmap` the replacements are batched like the
rest), each under its own source and named scopes (`jax.named_scope`), so that a profile
still names MJX's stages. An equation that a `Rule` applies to is computed by the rule; every
other one is bound as traced. Rules reach into the closed sub-jaxprs of loops, conditionals
and jitted calls that hold an equation they apply to; the others are left as they are.

A rule can stop fitting the library it was written for. One that matches nothing in the
traced function, or whose computation raises (a primitive's parameters renamed, say), leaves
the traced equations in place and warns once: the function stays correct, only slower.
"""

import dataclasses
import functools
from typing import Callable, Sequence
import warnings

import jax
from jax.extend import core, source_info_util


@dataclasses.dataclass(frozen=True)
class Rule:
    """What to compute in place of the equations it applies to."""

    name: str
    """Named in the warning when the rule no longer fits."""
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
        applied = _Applied(rules)
        outputs = _evaluate(closed.jaxpr, closed.consts, jax.tree.leaves(args), applied)
        for rule in rules:
            if rule.name in applied.failed:
                _warn(rule, fn, f"failed ({applied.failed[rule.name]})")
            elif rule.name not in applied.matched:
                _warn(rule, fn, "found nothing to rewrite")
        return jax.tree.unflatten(jax.tree.structure(out_shape), outputs)

    return rewritten


@dataclasses.dataclass
class _Applied:
    """The rules of one rewrite, and which of them matched an equation or failed on one."""

    rules: tuple[Rule, ...]
    matched: set = dataclasses.field(default_factory=set)
    failed: dict = dataclasses.field(default_factory=dict)


def _warn(rule: Rule, fn: Callable, what: str) -> None:
    name = getattr(fn, "__qualname__", repr(fn))
    warnings.warn(f"the rewrite {rule.name!r} {what} in {name}; its library code runs instead",
                  RuntimeWarning, stacklevel=3)


def _rule_for(eqn, rules: tuple[Rule, ...]) -> Rule | None:
    return next((rule for rule in rules if rule.applies(eqn)), None)


@functools.lru_cache(maxsize=4096)
def _has_target(jaxpr: core.Jaxpr, rules: tuple[Rule, ...]) -> bool:
    return any(_rule_for(eqn, rules) is not None
               or any(_has_target(sub, rules) for sub in core.jaxprs_in_params(eqn.params))
               for eqn in jaxpr.eqns)


def _rewrite_closed(closed: core.ClosedJaxpr, applied: _Applied) -> core.ClosedJaxpr:
    """`closed` re-traced with its targets replaced (unchanged if it has none)."""
    if not _has_target(closed.jaxpr, applied.rules):
        return closed
    avals = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
             for a in closed.in_avals]
    return jax.make_jaxpr(
        lambda *xs: _evaluate(closed.jaxpr, closed.consts, xs, applied))(*avals)


def _rewrite_param(value, applied: _Applied):
    if isinstance(value, core.ClosedJaxpr):
        return _rewrite_closed(value, applied)
    if isinstance(value, tuple) and value and all(isinstance(v, core.ClosedJaxpr) for v in value):
        return tuple(_rewrite_closed(v, applied) for v in value)
    if isinstance(value, core.Jaxpr) and _has_target(value, applied.rules):
        raise NotImplementedError("an open sub-jaxpr holds an equation to rewrite")
    return value


def _bind(eqn, inputs, params) -> list:
    outputs = eqn.primitive.bind(*inputs, **eqn.primitive.get_bind_params(params))
    return outputs if eqn.primitive.multiple_results else [outputs]


def _evaluate(jaxpr: core.Jaxpr, consts, args, applied: _Applied) -> list:
    """Evaluates `jaxpr` on `args`, applying the rules and rewriting sub-jaxprs that need it."""
    values = dict(zip(jaxpr.constvars, consts))
    values.update(zip(jaxpr.invars, args))

    def read(var):
        return var.val if isinstance(var, core.Literal) else values[var]

    for eqn in jaxpr.eqns:
        inputs = [read(v) for v in eqn.invars]
        rule = _rule_for(eqn, applied.rules)
        name_stack = source_info_util.current_name_stack() + eqn.source_info.name_stack
        with source_info_util.user_context(eqn.source_info.traceback, name_stack=name_stack), \
                eqn.ctx.manager:
            if rule is None or rule.name in applied.failed:
                outputs = _bind(eqn, inputs, {k: _rewrite_param(v, applied)
                                              for k, v in eqn.params.items()})
            else:
                outputs = _computed(rule, eqn, inputs, applied)
        values.update(zip(eqn.outvars, outputs))
    return [read(v) for v in jaxpr.outvars]


def _computed(rule: Rule, eqn, inputs, applied: _Applied) -> list:
    """The rule's outputs for `eqn`; the equation as traced if the rule raises (recorded)."""
    try:
        params = {k: _rewrite_param(v, applied) for k, v in eqn.params.items()}
        outputs = rule.compute(eqn, inputs, params)
    except Exception as error:  # noqa: BLE001  (any failure falls back to the traced code)
        applied.failed[rule.name] = f"{type(error).__name__}: {error}"
        return _bind(eqn, inputs, eqn.params)
    applied.matched.add(rule.name)
    return outputs

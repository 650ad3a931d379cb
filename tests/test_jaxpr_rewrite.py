"""Tests for pgps_jax.envs.mjx_rewrites: the re-tracing pass, its fallback when a rule no longer
fits, and the physics step's unrolled line search and solver iterations."""

import functools
import re

import jax
from jax.extend import core
from jax.extend.core import primitives
import jax.numpy as jnp
import numpy as np
import pytest

from pgps_jax.envs import make_env, physics
from pgps_jax.envs.mjx_rewrites.line_search import unrolled_line_search
from pgps_jax.envs.mjx_rewrites.solver_loop import unrolled_solver
from pgps_jax.envs.mjx_rewrites.rewrite import Rule, rewrite

SIN_TO_COS = Rule(name="sin_to_cos", applies=lambda eqn: eqn.primitive is primitives.sin_p,
                  compute=lambda eqn, inputs, params: [jnp.cos(*inputs)])


def _nested(x):
    """sin inside a jitted function inside a scan inside a cond, and one at the top."""
    inner = jax.jit(lambda c: jnp.sin(c) + 1.0)

    def looped(x):
        return jax.lax.scan(lambda c, _: (inner(c), None), x, None, length=3)[0]
    return jax.lax.cond(x.sum() > -1e9, looped, lambda x: x, x) * jnp.sin(x)


def _numpy_nested(x, fn):
    """`_nested` in numpy with `fn` for sin."""
    looped = x
    for _ in range(3):
        looped = fn(looped) + 1.0
    return looped * fn(x)


def test_rule_replaces_every_call_under_vmap_and_in_sub_jaxprs():
    x = jnp.linspace(-1.0, 1.0, 6).reshape(2, 3)
    start = np.asarray(x, np.float64)
    np.testing.assert_allclose(jax.vmap(rewrite(_nested, [SIN_TO_COS]))(x),
                               _numpy_nested(start, np.cos), rtol=1e-6)
    np.testing.assert_allclose(jax.vmap(_nested)(x), _numpy_nested(start, np.sin), rtol=1e-6)


def test_equations_without_a_rule_are_bound_as_traced():
    x = jnp.arange(4.0)
    never = Rule(name="never", applies=lambda eqn: False,
                 compute=lambda eqn, inputs, params: [])
    with pytest.warns(RuntimeWarning, match="'never' found nothing to rewrite in _nested"):
        traced = jax.make_jaxpr(rewrite(_nested, [never]))(x)
    assert str(traced) == str(jax.make_jaxpr(_nested)(x))


def test_the_rewritten_code_keeps_its_named_scopes():
    """A profile of the rewritten physics still names MJX's stages: every equation, rewritten
    or not, in a sub-jaxpr or not, lowers under the scopes it was traced in."""
    def scoped(x):
        with jax.named_scope("outer"):
            y = jnp.exp(x)
            with jax.named_scope("inner"):
                return _nested(y) + jnp.sin(y)

    def op_names(fn):
        text = jax.jit(fn).lower(jnp.arange(3.0)).as_text(debug_info=True)
        return set(re.findall(r'loc\("([^"]*)"', text))

    traced, rewritten = op_names(scoped), op_names(rewrite(scoped, [SIN_TO_COS]))
    assert any("outer/inner/" in name and name.endswith("sin") for name in traced)
    assert any(name.endswith("outer/exp") for name in rewritten)
    assert any("outer/inner/" in name and name.endswith("cos") for name in rewritten)
    assert any("outer/inner/" in name and "while" in name for name in rewritten)


def test_a_rule_that_fails_leaves_the_traced_code_and_warns_once_per_trace():
    """A rule whose computation raises (as when a primitive's parameters are renamed) falls
    back to the equation as traced, everywhere, with one warning that names the error."""
    def broken(eqn, inputs, params):
        raise KeyError("left_side")
    rule = Rule(name="broken", applies=lambda eqn: eqn.primitive is primitives.sin_p,
                compute=broken)
    x = jnp.linspace(-1.0, 1.0, 4)
    with pytest.warns(RuntimeWarning, match=r"'broken' failed \(KeyError: 'left_side'\)") as seen:
        fallback = jax.vmap(rewrite(_nested, [rule]))(x[None])[0]
    assert len([w for w in seen if "broken" in str(w.message)]) == 1
    np.testing.assert_allclose(fallback, _numpy_nested(np.asarray(x, np.float64), np.sin),
                               rtol=1e-6)


def _step(env, unroll_line_search):
    return jax.jit(jax.vmap(functools.partial(physics.step_frames, env.mjx_model, n_frames=2,
                                              unroll_line_search=unroll_line_search,
                                              fused_solve=False)))


def _assert_same_physics_without_its_loop(env, looped, unrolled, steps: int):
    """`unrolled` (batched physics steps) lowers with no device loop but the frames' (a loop
    on the CPU, unrolled on a GPU) where `looped` has more, and gives the same states over
    `steps` calls from 3 reset states under random controls."""
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 3))
    controls = jax.random.uniform(jax.random.PRNGKey(1), (3, env.action_size), minval=-1,
                                  maxval=1)
    data = state.pipeline_state.replace(ctrl=controls)

    def loops(fn):   # in the program handed to XLA
        return len(re.findall(r"stablehlo\.while", fn.lower(data).as_text()))
    frame_loops = 0 if jax.default_backend() == "gpu" else 1
    assert loops(looped) > frame_loops and loops(unrolled) == frame_loops
    a, b = data, data
    for _ in range(steps):
        a, b = looped(a), unrolled(b)
    for field in ("qpos", "qvel", "qacc_warmstart"):
        np.testing.assert_allclose(getattr(b, field), getattr(a, field), rtol=1e-5, atol=1e-5)


def test_unrolled_line_search_is_the_same_physics_without_device_loops():
    """halfcheetah with one solver iteration (no solver loop): MJX's line search is a 4-step
    scan; unrolled, the env step lowers with no device loop but the frames' (a loop on the
    CPU, unrolled on a GPU) and gives the same states."""
    env = make_env("halfcheetah", iterations=1)
    _assert_same_physics_without_its_loop(env, _step(env, False), _step(env, True), steps=5)


def test_only_scans_as_long_as_the_line_search_are_unrolled():
    def scans(x):
        for length in (3, 4, 5):
            x = jax.lax.scan(lambda c, _: (c * 0.5, None), x, None, length=length)[0]
        return x
    rewritten = jax.make_jaxpr(rewrite(scans, [unrolled_line_search(4)]))(1.0)
    unroll = {e.params["length"]: e.params["unroll"] for e in rewritten.jaxpr.eqns
              if e.primitive is primitives.scan_p}
    assert unroll == {3: 1, 4: 4, 5: 1}


def test_the_switches_on_physics_reach_the_env_step():
    """`make_env(..., unroll_line_search=True)` unrolls its step's line search on any
    device; False keeps MJX's loop (the frame loop is the same in both)."""
    def scan_unrolls(env):
        state = env.reset(jax.random.PRNGKey(0))
        jaxpr = jax.make_jaxpr(env.step)(state, jnp.zeros(env.action_size))
        found = []

        def visit(jaxpr):
            for eqn in jaxpr.eqns:
                if eqn.primitive is primitives.scan_p:
                    found.append(eqn.params["unroll"] == eqn.params["length"])
                for sub in core.jaxprs_in_params(eqn.params):
                    visit(sub)
        visit(jaxpr.jaxpr)
        return found
    unrolled = scan_unrolls(make_env("hopper", unroll_line_search=True))
    kept = scan_unrolls(make_env("hopper", unroll_line_search=False))
    assert len(unrolled) == len(kept) and sum(unrolled) > sum(kept)


THRESHOLD, FACTOR = np.float32(0.5), np.float32(0.9)


def _solver_like(x):
    """A while loop shaped like MJX's solver: at most 3 trips, each with a 4-step scan (its
    "line search"), ending early per row once x is small, with arrays closed over in its
    condition and body; then a loop without a scan."""
    threshold, factor = jnp.asarray(THRESHOLD), jnp.asarray(FACTOR)

    def body(carry):
        i, x = carry
        x = jax.lax.scan(lambda c, _: (c * factor - 0.01, None), x, None, length=4)[0]
        return i + 1, x
    _, x = jax.lax.while_loop(lambda c: (c[0] < 3) & (c[1] > threshold), body, (0, x))
    return jax.lax.while_loop(lambda y: y < 10.0, lambda y: y + 4.0, x)


def test_unrolled_solver_keeps_each_row_on_its_own_trips():
    """Rows that stop after 0, 1, 2 or 3 trips get the loop's result, and only the loop
    holding the line-search scan is written out."""
    x = jnp.array([0.2, 0.6, 1.0, 5.0])
    rewritten = rewrite(_solver_like, [unrolled_solver(3, 4)])
    expected, trips = [], []
    for row in np.asarray(x, np.float64):
        trip = 0
        while trip < 3 and row > THRESHOLD:
            for _ in range(4):
                row = row * FACTOR - 0.01
            trip += 1
        while row < 10.0:
            row += 4.0
        expected.append(row)
        trips.append(trip)
    assert trips == [0, 1, 2, 3]
    np.testing.assert_allclose(jax.vmap(rewritten)(x), jax.vmap(_solver_like)(x), rtol=1e-6)
    np.testing.assert_allclose(jax.vmap(rewritten)(x), expected, rtol=1e-5)
    whiles = [e for e in jax.make_jaxpr(rewritten)(1.0).jaxpr.eqns
              if e.primitive is primitives.while_p]
    assert len(whiles) == 1   # the loop without a scan is left as it is
    assert not any(e.primitive is primitives.scan_p
                   for e in whiles[0].params["body_jaxpr"].jaxpr.eqns)


def test_unrolled_solver_leaves_a_loop_of_another_trip_limit():
    """A loop whose condition does not bound it by `iterations` trips keeps its loop."""
    with pytest.warns(RuntimeWarning, match="'unrolled_solver' found nothing to rewrite"):
        traced = jax.make_jaxpr(rewrite(_solver_like, [unrolled_solver(2, 4)]))(1.0)
    assert sum(e.primitive is primitives.while_p for e in traced.jaxpr.eqns) == 2


def test_unrolled_solver_is_the_same_ant_physics_without_its_loop():
    """ant (Newton, 3 iterations; Euler's one forward pass per physics step rather than RK4's
    four, for a quarter of the program to compile): the step with the solver's iterations
    written out lowers with no while loop left but the frames' and gives the same states."""
    env = make_env("ant", integrator="euler")

    def step(unroll_solver):
        return jax.jit(jax.vmap(functools.partial(
            physics.step_frames, env.mjx_model, n_frames=2, unroll_line_search=True,
            unroll_solver=unroll_solver, fused_solve=False)))
    _assert_same_physics_without_its_loop(env, step(False), step(True), steps=3)


def test_the_rewrites_follow_the_platform_by_default(monkeypatch):
    """With the switches left at None (the fused solve aside: `test_fused_solve` follows its
    default), a program for a GPU has none of the device loops of the ant's physics step
    (frames, solver iterations, line search); one for the CPU keeps them."""
    env = make_env("ant")
    data = env.reset(jax.random.PRNGKey(0)).pipeline_state

    def loops():
        step = jax.jit(functools.partial(physics.step_frames, env.mjx_model, n_frames=2,
                                         fused_solve=False))
        return len(re.findall(r"stablehlo\.while", step.lower(data).as_text()))
    monkeypatch.setattr(physics, "default_platform", lambda: "cpu")
    on_cpu = loops()
    monkeypatch.setattr(physics, "default_platform", lambda: "gpu")
    assert on_cpu > 1 and loops() == 0

"""Tests for pgps_jax.envs.jaxpr_rewrite and the physics step's unrolled line search."""

import functools
import re

import jax
from jax.extend.core import primitives
import jax.numpy as jnp
import numpy as np

from pgps_jax.envs import make_env, physics
from pgps_jax.envs.jaxpr_rewrite import Rule, rewrite

SIN_TO_COS = Rule(applies=lambda eqn: eqn.primitive is primitives.sin_p,
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
    never = Rule(applies=lambda eqn: False, compute=lambda eqn, inputs, params: [])
    assert str(jax.make_jaxpr(rewrite(_nested, [never]))(x)) == str(jax.make_jaxpr(_nested)(x))


def _step(env, unroll_line_search):
    return jax.jit(jax.vmap(functools.partial(physics.step_frames, env.mjx_model, n_frames=2,
                                              unroll_line_search=unroll_line_search)))


def test_unrolled_line_search_is_the_same_physics_without_device_loops():
    """halfcheetah: MJX's line search is a 4-step scan; unrolled, the env step compiles with
    no device loop but the frames' (a loop on the CPU, unrolled on a GPU) and gives the same
    states."""
    env = make_env("halfcheetah")
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 3))
    controls = jax.random.uniform(jax.random.PRNGKey(1), (3, env.action_size), minval=-1,
                                  maxval=1)
    data = state.pipeline_state.replace(ctrl=controls)
    looped, unrolled = _step(env, False), _step(env, True)
    assert env.mj_model.opt.ls_iterations <= physics.MAX_UNROLLED_SCAN

    def loops(fn):
        return len(re.findall(r"\bwhile\(", fn.lower(data).compile().as_text()))
    frame_loops = 0 if jax.default_backend() == "gpu" else 1
    assert loops(looped) > frame_loops and loops(unrolled) == frame_loops
    a, b = data, data
    for _ in range(5):
        a, b = looped(a), unrolled(b)
    for field in ("qpos", "qvel", "qacc_warmstart"):
        np.testing.assert_allclose(getattr(b, field), getattr(a, field), rtol=1e-5, atol=1e-5)


def test_long_scans_stay_loops():
    def long_scan(x):
        return jax.lax.scan(lambda c, _: (c * 0.5, None), x, None,
                            length=physics.MAX_UNROLLED_SCAN + 1)[0]
    rewritten = jax.make_jaxpr(rewrite(long_scan, [physics.UNROLLED_LINE_SEARCH]))(1.0)
    (eqn,) = [e for e in rewritten.jaxpr.eqns if e.primitive is primitives.scan_p]
    assert eqn.params["unroll"] == 1

"""The Newton solve as one kernel per env (`mjx_rewrites.fused_solve`): MJX's solve to float
tolerance, the same env steps, a GPU program that lowers, and a clear refusal of what it does
not cover. On a CPU the kernel runs interpreted."""

import functools
import threading

import jax
from jax import export
import jax.numpy as jnp
from mujoco import mjx
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import solver as mjx_solver
import numpy as np
import pytest

from pgps_jax.envs import make_env, mjx_rewrites, physics
from pgps_jax.envs.mjx_rewrites import fused_solve

TRITON_CALL = "__gpu$xla.gpu.triton"
OPTIMISED = {"xla_backend_optimization_level": 2}
"""XLA's default optimisation, for the programs that interpret the kernel on the CPU: at level
0 (the tests' fast-compile flags) XLA's CPU backend miscompiles them (a line-search point's
cost taken from another point; the same code run op by op, or compiled at level 1 or more,
gives MJX's result)."""


def _optimised(fn, *args):
    """`fn(*args)`, compiled with `OPTIMISED`."""
    return jax.jit(fn).lower(*args).compile(compiler_options=OPTIMISED)(*args)


@functools.lru_cache(maxsize=None)
def _states_before_solving(env, batch: int = 16, steps: int = 25):
    """Batched MJX data after `steps` env steps under random actions, with the forward
    dynamics up to the solve done (its inputs: constraint rows, smooth terms, warm start).
    Made once per env in a worker: the ant's two solver settings below solve the same
    states."""
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch))
    step = jax.jit(jax.vmap(env.step))
    for k in range(steps):
        state = step(state, jax.random.uniform(jax.random.PRNGKey(k), (batch, env.action_size),
                                               minval=-1, maxval=1))
    m = env.mjx_model

    def before_solving(d):
        for stage in (mjx_forward.fwd_position, mjx_forward.fwd_velocity,
                      mjx_forward.fwd_actuation, mjx_forward.fwd_acceleration):
            d = stage(m, d)
        return d
    return jax.jit(jax.vmap(before_solving))(state.pipeline_state)


@pytest.mark.xdist_group("fused_solve")  # on one worker, which steps the ant's states once
@pytest.mark.parametrize("task, iterations", [("ant", 3), ("ant", 1), ("hopper", 1)])
def test_the_fused_solve_is_mjx_solve(task, iterations):
    """ant (108 constraint rows padded to 128, 14 dofs to 16; its 3 iterations, and one,
    where the line search's result is the step's) and hopper (one iteration): qacc, the
    constraint force and each row's force as MJX's solve gives them, from its warm start
    (states reached with Euler's integrator, one forward pass per frame: the solve is the
    same for RK4's)."""
    env = make_env(task, integrator="euler")
    m, data = env.mjx_model, _states_before_solving(env)
    m = m.tree_replace({"opt.iterations": iterations})
    # reference accelerations pushed about, so that rows turn active and inactive along the
    # line search's direction and its bracketing runs (at these states it rarely needs to)
    aref = data._impl.efc_aref
    scale = jnp.abs(aref).max(axis=-1, keepdims=True)
    data = data.tree_replace({"_impl.efc_aref": aref + scale * jax.random.normal(
        jax.random.PRNGKey(2), aref.shape)})
    rows = int(data._impl.efc_J.shape[-2])
    assert fused_solve._padded(rows) > rows   # the kernel's tiles hold padding rows
    ours = _optimised(jax.vmap(functools.partial(fused_solve.solve, m, interpret=True)), data)
    theirs = jax.vmap(functools.partial(mjx_solver.solve, m))(data)
    for got, expected in ((ours.qacc, theirs.qacc),
                          (ours.qfrc_constraint, theirs.qfrc_constraint),
                          (ours._impl.efc_force, theirs._impl.efc_force)):
        expected = np.asarray(expected)   # each env to its own scale
        error = np.abs(np.asarray(got) - expected)
        scale = np.abs(expected).max(axis=-1, keepdims=True)
        np.testing.assert_array_less(error, np.broadcast_to(1e-5 * scale + 1e-6, error.shape))


def test_the_env_step_with_the_fused_solve_is_the_same_physics():
    """The ant's env step (5 frames, each one forward pass with Euler's integrator: RK4's four
    solve alike) with `fused_solve=true` plays the same states as without over three steps."""
    states = []
    for fused in (False, True):
        env = make_env("ant", fused_solve=fused, integrator="euler")
        state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 3))
        actions = jax.random.uniform(jax.random.PRNGKey(1), (3, 3, env.action_size),
                                     minval=-1, maxval=1)
        play = lambda s, a: jax.lax.scan(lambda s, a: (jax.vmap(env.step)(s, a), None), s, a)[0]
        states.append(_optimised(play, state, actions))
    np.testing.assert_allclose(states[1].obs, states[0].obs, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("task, settings, fused", [
    ("ant", {}, True), ("hopper", {}, True), ("hopper", {"matmul_precision": "default"}, False),
    ("hopper", {"solver": "cg"}, False),
])
def test_a_gpu_s_env_step_solves_in_a_triton_kernel_by_default(task, settings, fused,
                                                                monkeypatch):
    """Lowered for CUDA (no GPU needed), the default env step holds the solve as a Triton
    kernel and no device loop: the kernel's code is within what Pallas can lower to Triton,
    also beside the written-out factorisations that a GPU gets (hopper: 6 dofs). With TF32
    products around it (matmul_precision=default), or for a solver it does not cover, MJX's
    own solve stays."""
    monkeypatch.setattr(physics, "default_platform", lambda: "gpu")
    env = make_env(task, **settings)
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    lowered = export.export(
        jax.jit(jax.vmap(env.step)), platforms=["cuda"],
        disabled_checks=[export.DisabledSafetyCheck.custom_call(TRITON_CALL)],
    )(state, jnp.zeros((2, env.action_size))).mlir_module()
    assert (TRITON_CALL in lowered) == fused
    assert fused <= ("stablehlo.while" not in lowered)
    assert physics.resolved(env.physics, env.mjx_model).fused_solve == fused  # as recorded
    monkeypatch.setattr(physics, "default_platform", lambda: "cpu")
    assert not physics.resolved(env.physics, env.mjx_model).fused_solve


@pytest.mark.parametrize("settings, named", [
    (dict(solver="cg"), "the solver is not Newton's"),
    (dict(impl="warp"), "not Warp's"),
])
def test_the_fused_solve_refuses_what_it_does_not_cover(settings, named):
    with pytest.raises(ValueError, match=named):
        make_env("hopper", fused_solve=True, **settings)


def test_physics_step_refuses_the_fused_solve_for_a_model_it_does_not_cover():
    model = make_env("hopper", solver="cg").mjx_model
    with pytest.raises(ValueError, match="the solver is not Newton's"):
        mjx_rewrites.physics_step(model, False, False, False, fused_solve=True, on_gpu=False)


def test_the_solve_is_replaced_in_the_thread_that_asks_alone():
    """While one thread traces MJX's step with `solve_replaced` open, another traces MJX's own
    solve; once closed, the first does too."""
    model = make_env("hopper").mjx_model
    data = mjx.make_data(model)
    kernels = lambda: "pallas_call" in str(jax.make_jaxpr(functools.partial(mjx.step, model))(
        data))
    elsewhere = []
    with fused_solve.solve_replaced(interpret=True):
        other = threading.Thread(target=lambda: elsewhere.append(kernels()))
        other.start()
        other.join()
        here = kernels()
    assert (here, elsewhere, kernels()) == (True, [False], False)

"""Tests for pgps_jax.envs: the registry, the five MuJoCo tasks on MJX and the NaN guard.

Each task's batched reset and step are jitted once (module-scoped fixtures) and reused, its
tests on one pytest-xdist worker (a group per task) so that no other worker compiles them again.
"""

import types

from brax.envs.base import State
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from pgps_jax.envs import TASKS, make_env, nan_guard, physics

N_ENVS = 4
N_STEPS = 200
# Gym v4: (observation size, action size, dt = timestep × frame_skip, ctrl cost weight).
GYM_V4 = {
    "halfcheetah": (17, 6, 0.01 * 5, 0.1),
    "hopper": (11, 3, 0.002 * 4, 1e-3),
    "walker2d": (17, 6, 0.002 * 4, 1e-3),
    "ant": (27, 8, 0.01 * 5, 0.5),
    "swimmer": (8, 2, 0.01 * 4, 1e-4),
}
TERMINATING = ("hopper", "walker2d", "ant")


@pytest.fixture(scope="module", params=[
    pytest.param(name, marks=pytest.mark.xdist_group(f"env_{name}")) for name in TASKS])
def task(request):
    env = make_env(request.param)
    return types.SimpleNamespace(name=request.param, env=env,
                                 reset=jax.jit(jax.vmap(env.reset)),
                                 step=jax.jit(jax.vmap(env.step)))


@pytest.fixture(scope="module")
def trajectory(task):
    """N_STEPS of uniform random actions from reset, stepping on past any termination."""
    key_reset, key_actions = jax.random.split(jax.random.PRNGKey(0))
    state = task.reset(jax.random.split(key_reset, N_ENVS))
    actions = jax.random.uniform(key_actions, (N_STEPS, N_ENVS, task.env.action_size),
                                 minval=-1.2, maxval=1.2)
    states = [state]
    for action in actions:
        states.append(task.step(states[-1], action))
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *states)
    return types.SimpleNamespace(states=stacked, actions=np.asarray(actions))


def _reset(task, seed=0):
    return task.reset(jax.random.split(jax.random.PRNGKey(seed), N_ENVS))


def _with(state, field, row, index, value):
    """`state` with pipeline_state.<field>[row, index] = value."""
    data = state.pipeline_state
    array = getattr(data, field).at[row, index].set(value)
    return state.replace(pipeline_state=data.replace(**{field: array}))


def test_unknown_task_lists_every_task():
    with pytest.raises(ValueError) as error:
        make_env("cheetah")
    for name in TASKS + ("point", "'cheetah'"):
        assert name in str(error.value)


def test_start_pose_is_qpos0_or_brax_keyframe():
    """Gym resets around qpos0 (ant: torso at 0.75 m, legs flat); ant's model also has Brax's
    `init_qpos` keyframe (torso at 0.55 m, legs bent). Models without a keyframe start at
    qpos0 either way."""
    keyframe, gym = make_env("ant", start_pose="init_qpos"), make_env("ant")
    assert float(keyframe._init_qpos[2]) == pytest.approx(0.55)
    np.testing.assert_array_equal(gym._init_qpos, gym.mj_model.qpos0)
    assert float(gym._init_qpos[2]) == pytest.approx(0.75)
    np.testing.assert_array_equal(make_env("hopper")._init_qpos,
                                  make_env("hopper", start_pose="init_qpos")._init_qpos)
    with pytest.raises(ValueError, match="start_pose 'bent'; valid: qpos0, init_qpos"):
        make_env("ant", start_pose="bent")


def test_settings_given_or_left_to_the_task_s_defaults_build_one_env():
    """Equal settings, given or the task's defaults, give the same env object (and its
    compiled programs); other settings another."""
    hopper = make_env("hopper")
    assert make_env("hopper", start_pose="qpos0", integrator="euler", fused_solve=None) is hopper
    assert make_env("hopper", **hopper.settings()) is hopper
    assert make_env("hopper", iterations=2) is not hopper
    assert make_env("ant", start_pose="init_qpos") is not make_env("ant")


def test_brax_asset_warnings_are_dropped_and_others_shown(capfd):
    make_env("halfcheetah")  # Brax's half_cheetah.xml sets the deprecated settotalmass
    with physics._known_warnings_dropped():
        mujoco.get_mju_user_warning()("compiler attribute 'settotalmass' is deprecated ...")
        mujoco.get_mju_user_warning()("something else")
    out, err = capfd.readouterr()
    assert "settotalmass" not in out + err
    assert "WARNING: something else" in err
    assert mujoco.get_mju_user_warning() is None  # MuJoCo's own handler is back


def test_physics_overrides_reach_the_model():
    env = make_env("hopper", iterations=3, ls_iterations=7, euler_damping=True,
                   integrator="rk4")
    assert (env.mj_model.opt.iterations, env.mj_model.opt.ls_iterations) == (3, 7)
    assert env.mj_model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert make_env("hopper").mj_model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert (make_env("hopper", integrator="implicitfast").mj_model.opt.integrator
            == mujoco.mjtIntegrator.mjINT_IMPLICITFAST)
    assert not env.mj_model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    assert make_env("hopper").mj_model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    with pytest.raises(TypeError):
        make_env("hopper", substeps=2)
    with pytest.raises(ValueError, match="solver"):
        make_env("hopper", solver="pgs")
    with pytest.raises(ValueError, match="iterations must be an integer, got 2.0"):
        make_env("hopper", iterations=2.0)
    with pytest.raises(ValueError, match="euler_damping must be true or false, got 0"):
        make_env("hopper", euler_damping=0)  # not the default's env: False == 0
    with pytest.raises(ValueError,
                       match="integrator must be one of .'euler', 'implicitfast', 'rk4'."):
        make_env("hopper", integrator="implicit")


def test_the_physics_multiplies_in_float32_unless_told_otherwise():
    """Every matrix product of the env step asks for float32 (HIGHEST: a GPU would otherwise
    round its inputs to TF32); with matmul_precision=default none does."""
    for precision, highest in (("highest", True), ("default", False)):
        env = make_env("hopper", matmul_precision=precision)
        state = env.reset(jax.random.PRNGKey(0))
        lowered = jax.jit(env.step).lower(state, jnp.zeros(env.action_size)).as_text()
        products = [line for line in lowered.splitlines() if "dot_general" in line]
        assert len(products) > 10
        assert [("HIGHEST" in line) for line in products] == [highest] * len(products)
    with pytest.raises(ValueError, match="matmul_precision must be one of highest, default"):
        make_env("hopper", matmul_precision="tensorfloat32")
    with pytest.raises(ValueError, match="fused_solve computes in float32.*"
                                         "matmul_precision=highest or fused_solve=false"):
        make_env("hopper", matmul_precision="default", fused_solve=True)


def _floor_contacts(env, torso_z: float) -> set[str]:
    """Names of the geoms touching the floor with the ant's torso lowered to `torso_z`."""
    model = env.mj_model
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    data.qpos[2] = torso_z
    mujoco.mj_forward(model, data)
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    names = set()
    for contact in data.contact[:data.ncon]:
        other = contact.geom2 if contact.geom1 == floor else contact.geom1
        names.add(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, other))
    return names


def test_floor_contacts_of_the_model_or_of_gym():
    """Brax's ant lets only four added zero-mass foot spheres touch the floor; with
    floor_contacts="gym" (the ant's default) the spheres are gone and the torso and legs touch
    it, with a margin of 0.01 m, and no geom touches another: Gym's ant, the same geoms and
    masses."""
    feet = {f"{side}_foot_geom" for side in ("left", "right", "third", "fourth")}
    brax = make_env("ant", floor_contacts="model")
    assert _floor_contacts(brax, 0.05) == feet
    gym = make_env("ant")
    touching = _floor_contacts(gym, 0.05)
    assert {"torso_geom", "aux_1_geom", "left_ankle_geom"} <= touching
    assert not touching & feet
    assert gym.mj_model.ngeom == brax.mj_model.ngeom - 4
    np.testing.assert_allclose(gym.mj_model.body_mass, brax.mj_model.body_mass)
    assert np.all(gym.mj_model.geom_margin == 0.01)
    assert _floor_contacts(gym, 0.5) == set()  # 0.25 m above the floor: none
    with pytest.raises(ValueError, match="model, gym"):
        make_env("ant", floor_contacts="all")


def test_shapes_and_dtypes(task):
    obs_size, action_size, dt, _ = GYM_V4[task.name]
    env = task.env
    assert (env.observation_size, env.action_size) == (obs_size, action_size)
    assert env.dt == pytest.approx(dt)
    state = _reset(task)
    step = task.step(state, jnp.zeros((N_ENVS, action_size)))
    for s in (state, step):
        assert s.obs.shape == (N_ENVS, obs_size) and s.obs.dtype == jnp.float32
        for x in (s.reward, s.done, s.metrics["unstable"]):
            assert x.shape == (N_ENVS,) and x.dtype == jnp.float32
        assert jax.tree.structure(s) == jax.tree.structure(state)
    np.testing.assert_array_equal(state.metrics["unstable"], 0.0)
    np.testing.assert_array_equal(state.done, 0.0)


def test_random_steps_stay_finite(task, trajectory):
    states = trajectory.states
    assert np.isfinite(states.obs).all() and np.isfinite(states.reward).all()
    assert np.isfinite(states.pipeline_state.qpos).all()
    np.testing.assert_array_equal(states.metrics["unstable"], 0.0)
    if task.name not in TERMINATING:
        np.testing.assert_array_equal(states.done, 0.0)


def test_reward_is_gym_v4(task, trajectory):
    """Forward term = Δ(torso x by MuJoCo's kinematics)/dt; reward = forward + healthy − ctrl."""
    _, _, dt, ctrl_weight = GYM_V4[task.name]
    states, model = trajectory.states, task.env.mj_model
    data = mujoco.MjData(model)

    def torso_x(qpos):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        return data.body("torso").xpos[0]

    qpos = states.pipeline_state.qpos
    x = np.array([[torso_x(q) for q in qpos_t] for qpos_t in qpos])
    metrics = states.metrics
    np.testing.assert_allclose(metrics["reward_forward"][1:], (x[1:] - x[:-1]) / dt,
                               rtol=1e-4, atol=1e-4)
    ctrl = -ctrl_weight * np.sum(np.clip(trajectory.actions, -1, 1) ** 2, axis=-1)
    np.testing.assert_allclose(metrics["reward_ctrl"][1:], ctrl, rtol=1e-5, atol=1e-6)
    healthy = 1.0 if task.name in TERMINATING else 0.0
    np.testing.assert_array_equal(metrics["reward_healthy"][1:], healthy)
    np.testing.assert_allclose(states.reward[1:], metrics["reward_forward"][1:] + healthy + ctrl,
                               rtol=1e-5, atol=1e-5)


def test_termination_leaves_healthy_range(task):
    """Row 0 stays healthy; each other row breaks one of the task's health conditions."""
    state = _reset(task)
    if task.name == "hopper":
        state = _with(state, "qpos", 1, 1, -0.6)  # torso z 0.65 < 0.7
        state = _with(state, "qpos", 2, 2, 0.3)  # torso angle > 0.2
        state = _with(state, "qvel", 3, 0, 150.0)  # a state entry beyond 100
    elif task.name == "walker2d":
        state = _with(state, "qpos", 1, 1, -0.5)  # torso z 0.75 < 0.8
        state = _with(state, "qpos", 2, 1, 0.9)  # torso z 2.15 > 2.0
        state = _with(state, "qpos", 3, 2, -1.2)  # torso angle < -1
    elif task.name == "ant":
        state = _with(state, "qpos", 1, 2, 1.05)  # torso z > 1.0
        state = _with(state, "qpos", 2, 2, 1.5)
        state = _with(state, "qvel", 3, 2, 15.0)  # jumps above 1.0 within the step
    step = task.step(state, jnp.zeros((N_ENVS, task.env.action_size)))
    expected = [0.0, 1.0, 1.0, 1.0] if task.name in TERMINATING else [0.0] * N_ENVS
    np.testing.assert_array_equal(step.done, expected)
    np.testing.assert_array_equal(step.metrics["unstable"], 0.0)


@pytest.mark.parametrize("name, index, healthy, unhealthy", [
    ("hopper", 1, [-0.54, 0.5], [-0.56]),  # z = 1.25 + qpos[1] > 0.7
    ("hopper", 2, [-0.19, 0.19], [-0.21, 0.21]),  # |torso angle| < 0.2
    ("walker2d", 1, [-0.44, 0.74], [-0.46, 0.76]),  # 0.8 < z < 2.0
    ("walker2d", 2, [-0.99, 0.99], [-1.01, 1.01]),  # |torso angle| < 1.0
    ("ant", 2, [0.2, 0.6, 1.0], [0.19, 1.01]),  # 0.2 <= z <= 1.0
])
def test_healthy_range_boundaries(name, index, healthy, unhealthy):
    env = make_env(name)
    qpos, qvel = jnp.asarray(physics.init_qpos(env.mj_model)), jnp.zeros(env.mj_model.nv)
    for value, expected in [(v, True) for v in healthy] + [(v, False) for v in unhealthy]:
        assert bool(env.is_healthy(qpos.at[index].set(value), qvel)) == expected, value


def test_reset_is_deterministic(task):
    first, again, other = _reset(task, 1), _reset(task, 1), _reset(task, 2)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    assert not np.allclose(first.obs, other.obs)
    assert np.unique(np.asarray(first.obs), axis=0).shape[0] == N_ENVS


def test_nan_guard_drops_poisoned_steps(task):
    """A NaN action (row 1) or NaN velocity (row 2) ends that episode and nothing else."""
    state = _reset(task)
    data = state.pipeline_state
    state = state.replace(pipeline_state=data.replace(qvel=data.qvel.at[2].set(jnp.nan)))
    action = jnp.full((N_ENVS, task.env.action_size), 0.5, jnp.float32).at[1, 0].set(jnp.nan)
    step = task.step(state, action)
    np.testing.assert_array_equal(step.metrics["unstable"], [0.0, 1.0, 1.0, 0.0])
    np.testing.assert_array_equal(step.done[1:3], 1.0)
    np.testing.assert_array_equal(step.reward[1:3], 0.0)
    assert np.isfinite(step.obs).all()
    np.testing.assert_array_equal(step.obs[1], state.obs[1])
    np.testing.assert_array_equal(step.pipeline_state.qpos[1], state.pipeline_state.qpos[1])
    # The kept physics of row 1 steps on finitely.
    after = task.step(step, jnp.zeros((N_ENVS, task.env.action_size)))
    assert np.isfinite(after.pipeline_state.qpos[np.array([0, 1, 3])]).all()
    np.testing.assert_array_equal(after.metrics["unstable"][np.array([0, 1, 3])], 0.0)


def test_guard_keeps_previous_state():
    prev = State(pipeline_state={"q": jnp.ones(2)}, obs=jnp.ones(3), reward=jnp.ones(()),
                 done=jnp.zeros(()), metrics={"unstable": jnp.zeros(()), "x": jnp.ones(())})
    new = prev.replace(pipeline_state={"q": jnp.full(2, jnp.nan)}, obs=jnp.full(3, jnp.nan),
                       reward=jnp.array(jnp.nan), metrics={"unstable": jnp.zeros(()),
                                                           "x": jnp.array(jnp.inf)})
    assert not nan_guard.all_finite(new.pipeline_state, new.obs)
    assert nan_guard.all_finite(prev.pipeline_state, prev.obs, jnp.arange(3))
    out = nan_guard.guard(prev, new, nan_guard.all_finite(new.pipeline_state))
    np.testing.assert_array_equal(out.pipeline_state["q"], 1.0)
    np.testing.assert_array_equal(out.obs, 1.0)
    assert (out.reward, out.done, out.metrics["unstable"], out.metrics["x"]) == (0, 1, 1, 1)
    kept = nan_guard.guard(prev, prev.replace(reward=jnp.array(2.0)), jnp.array(True))
    assert (kept.reward, kept.done, kept.metrics["unstable"]) == (2, 0, 0)


def test_step_inside_while_loop():
    """A task steps under jit(vmap(...)) inside lax.while_loop until every env is done."""
    env = make_env("hopper")

    @jax.jit
    def until_done(key):
        state = jax.vmap(env.reset)(jax.random.split(key, N_ENVS))

        def body(carry):
            t, state, ended = carry
            state = jax.vmap(env.step)(state, jnp.ones((N_ENVS, env.action_size)))
            return t + 1, state, jnp.maximum(ended, state.done)

        return jax.lax.while_loop(lambda c: (c[0] < 500) & ~jnp.all(c[2] > 0), body,
                                  (0, state, jnp.zeros(N_ENVS)))

    t, state, ended = until_done(jax.random.PRNGKey(0))
    assert 0 < int(t) < 500 and np.all(ended == 1.0)
    assert np.isfinite(state.obs).all()


def test_brax_training_wrappers_run_our_task():
    """Brax's own wrappers (vmap, episode limit, auto-reset) accept the task: the metrics
    they add survive our step, and the episode limit truncates and restarts."""
    from brax.envs.wrappers import training as brax_training
    env = brax_training.wrap(make_env("swimmer"), episode_length=3)
    state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    step = jax.jit(env.step)
    steps, truncated = [], []
    for _ in range(4):
        state = step(state, jnp.zeros((2, env.action_size)))
        steps.append(np.asarray(state.info["steps"]))
        truncated.append(np.asarray(state.info["truncation"]))
    np.testing.assert_array_equal(np.stack(steps)[:, 0], [1, 2, 3, 1])  # restarted after 3
    np.testing.assert_array_equal(np.stack(truncated)[:, 0], [0, 0, 1, 0])
    assert "unstable" in state.metrics and np.isfinite(state.obs).all()


@pytest.mark.parametrize("declared", [1, 4])
def test_an_action_size_that_the_physics_does_not_take_is_named(declared):
    """One action would broadcast into hopper's three controls and train silently."""
    from pgps_jax.agent.rollout import random_warmup

    env = make_env("hopper")
    mis_declared = type("MisDeclared", (type(env),),
                        {"action_size": property(lambda self: declared)})
    env = mis_declared(**type(env).constructor_arguments())
    with pytest.raises(ValueError, match=rf"controls of shape \(3,\) \(pipeline_state.ctrl\) "
                                         rf"but the env declares action_size {declared}"):
        jax.eval_shape(lambda key: random_warmup(env, key, 2, 2, 2), jax.random.PRNGKey(0))

"""A Gym-MuJoCo-v4-style locomotion task as a Brax `Env` that steps MJX directly.

Shared by the five tasks: reset noise around the model's initial pose, `n_frames` physics
steps per action, reward = forward_weight·Δx/dt + healthy_reward − ctrl_weight·Σa², and
termination when a task's `is_healthy` test fails. There is no time limit and no auto-reset
(the rollout truncates episodes). A non-finite step is terminal (`nan_guard`).
"""

import dataclasses

from brax.envs.base import Env, State
import jax
import jax.numpy as jnp

from pgps_jax.envs import nan_guard, physics
from pgps_jax.envs.physics import Physics

START_POSES = ("qpos0", "init_qpos")
"""Reset poses: the model's reference pose qpos0, as Gym's MuJoCo envs reset; or Brax's
`init_qpos` keyframe where the model has one (ant), else qpos0."""


def check_start_pose(start_pose: str) -> None:
    """A ValueError naming the choices unless `start_pose` is one of `START_POSES`."""
    if start_pose not in START_POSES:
        raise ValueError(f"unknown start_pose {start_pose!r}; valid: {', '.join(START_POSES)}")


METRICS = ("x_position", "x_velocity", "reward_forward", "reward_ctrl", "reward_healthy",
           "unstable")


class MjxEnv(Env):
    """Base class; a task sets the class attributes and the observation / health tests."""

    xml: str
    """Brax asset file."""
    n_frames: int
    """Physics steps per env step (Gym's frame_skip)."""
    default_physics: Physics
    """Solver settings chosen for the task (see BENCHMARKS.md)."""
    forward_reward_weight: float = 1.0
    ctrl_cost_weight: float
    healthy_reward: float = 0.0
    """Paid every step, the terminal one included (Gym v4 with terminate_when_unhealthy)."""
    reset_noise_scale: float
    qvel_noise_normal: bool = False
    """Reset velocity noise ~ scale·N(0, 1) (HalfCheetah, Ant) instead of U(±scale)."""

    def __init__(self, start_pose: str = "qpos0", **physics_overrides):
        """`start_pose`: the pose that reset adds noise to, one of `START_POSES`;
        `physics_overrides`: fields of `Physics` replacing the task's defaults."""
        check_start_pose(start_pose)
        self.start_pose = start_pose
        self.physics = dataclasses.replace(self.default_physics, **physics_overrides)
        self.mj_model, self.mjx_model = physics.load_model(self.xml, self.physics)
        pose = (physics.init_qpos(self.mj_model) if start_pose == "init_qpos"
                else self.mj_model.qpos0)
        self._init_qpos = jnp.asarray(pose)
        self._data0 = physics.make_data(self.mj_model, self.physics.impl)

    @classmethod
    def constructor_arguments(cls, start_pose: str = "qpos0", **physics_overrides) -> dict:
        """Every argument of the constructor at the value it takes for these: `start_pose`
        and each `Physics` field, the task's default where not given (ValueError or
        TypeError as the constructor raises them)."""
        physics = dataclasses.replace(cls.default_physics, **physics_overrides)
        return {"start_pose": start_pose, **dataclasses.asdict(physics)}

    def settings(self) -> dict:
        """What the simulated task depends on beyond its class: the start pose and the
        physics settings (`Physics.model_settings`)."""
        return {"start_pose": self.start_pose, **self.physics.model_settings()}

    @property
    def dt(self) -> float:
        """Seconds per env step: timestep × n_frames."""
        return float(self.mj_model.opt.timestep) * self.n_frames

    def reset(self, rng: jax.Array) -> State:
        """Initial pose plus noise (Gym v4 `reset_model`).

        Only qpos and qvel are set: the first `mjx.step` derives everything else from them, so
        reset compiles and runs without a forward pass (call `mjx.forward` to inspect or render
        the reset state's kinematics).
        """
        key_q, key_v = jax.random.split(rng)
        scale = self.reset_noise_scale
        qpos = self._init_qpos + jax.random.uniform(
            key_q, (self.mj_model.nq,), minval=-scale, maxval=scale)
        if self.qvel_noise_normal:
            qvel = scale * jax.random.normal(key_v, (self.mj_model.nv,))
        else:
            qvel = jax.random.uniform(key_v, (self.mj_model.nv,), minval=-scale, maxval=scale)
        data = self._data0.replace(qpos=qpos, qvel=qvel)
        metrics = {k: jnp.zeros((), jnp.float32) for k in METRICS}
        metrics["x_position"] = self._x_position(qpos)
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=data, obs=self.observation(data.qpos, data.qvel),
                     reward=zero, done=zero, metrics=metrics, info={})

    def step(self, state: State, action: jax.Array) -> State:
        """One env step: clip the action to [-1, 1], n_frames physics steps, reward, done."""
        action = jnp.clip(action, -1.0, 1.0)
        data0 = state.pipeline_state
        data = physics.step_frames(self.mjx_model, data0.replace(ctrl=action), self.n_frames,
                                   self.physics.write_out_linalg,
                                   self.physics.unroll_line_search,
                                   self.physics.unroll_solver, self.physics.fused_solve,
                                   self.physics.matmul_precision)
        terms = self.reward_terms(data0.qpos, data.qpos, action)
        obs = self.observation(data.qpos, data.qvel)
        new = state.replace(
            pipeline_state=data, obs=obs, reward=self.reward(terms),
            done=1.0 - self.is_healthy(data.qpos, data.qvel).astype(jnp.float32),
            metrics={**state.metrics,  # keep keys that Brax wrappers add
                     **terms, "unstable": jnp.zeros((), jnp.float32)})
        finite = nan_guard.all_finite(data.qpos, data.qvel, obs, new.reward)
        return nan_guard.guard(state, new, finite)

    def reward_terms(self, qpos0: jax.Array, qpos1: jax.Array, action: jax.Array) -> dict:
        """Gym v4's reward terms of a step from `qpos0` to `qpos1` under (clipped) `action`,
        and the forward coordinate and velocity they come from."""
        x0, x1 = self._x_position(qpos0), self._x_position(qpos1)
        x_velocity = (x1 - x0) / self.dt
        return dict(x_position=x1, x_velocity=x_velocity,
                    reward_forward=self.forward_reward_weight * x_velocity,
                    reward_ctrl=-self.ctrl_cost_weight * jnp.sum(jnp.square(action)),
                    reward_healthy=jnp.asarray(self.healthy_reward, jnp.float32))

    @staticmethod
    def reward(terms: dict) -> jax.Array:
        """forward + healthy + ctrl (the ctrl term negative)."""
        return terms["reward_forward"] + terms["reward_healthy"] + terms["reward_ctrl"]

    def _x_position(self, qpos: jax.Array) -> jax.Array:
        """Forward coordinate whose rate is rewarded: qpos[0], the root joint's x (Gym v4)."""
        return qpos[0]

    def observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        """The task's Gym v4 observation of the physics state."""
        raise NotImplementedError

    def is_healthy(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        """Gym v4's `is_healthy`; False ends the episode. Tasks without termination: True."""
        return jnp.array(True)

    @property
    def observation_size(self) -> int:
        return int(jax.eval_shape(self.observation, self._data0.qpos, self._data0.qvel).shape[-1])

    @property
    def action_size(self) -> int:
        return int(self.mj_model.nu)

    @property
    def backend(self) -> str:
        return "mjx"

"""Hopper: Gym `Hopper-v4` on Brax's `hopper.xml`, stepped on MJX.

Brax's model drops the `ref` of the rootz joint, so the torso height is z = 1.25 + qpos[1]
(Gym's qpos[1] is the height itself), and integrates with Euler where Gym's asks for RK4.

- Observation (11): z, qpos[2:] (torso angle, thigh, leg, foot angles), then
  clip(qvel, −10, 10) (6).
- Action (3): thigh, leg, foot torques in [-1, 1].
- Reward: 1.0·Δx/dt + 1.0 (healthy, paid every step) − 1e-3·Σa², x = qpos[0] (rootx).
- Termination: unless z > 0.7, |torso angle qpos[2]| < 0.2 and every entry of
  (qpos[2:], qvel) lies in (−100, 100).
- dt: 0.002 s timestep × frame_skip 4 = 0.008 s.
- Reset: qpos0 + U(±5e-3), qvel = U(±5e-3).
- Physics: Newton, 1 iteration, 4 line-search iterations, Euler damping off. It carries
  the PGPS authors' trained hopper (3,730 over 30 episodes, none ended early; the model's
  converged solve 3,254, 12 ended) and moves random actions and sinusoids within 3% and 7%
  of the model's own settings (BENCHMARKS.md).
"""

import jax
import jax.numpy as jnp

from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.physics import Physics

_TORSO_Z0 = 1.25
_MIN_Z = 0.7
_MAX_ANGLE = 0.2
_MAX_STATE = 100.0


class Hopper(MjxEnv):
    """Hopper-v4; see the module docstring for its terms."""

    xml = "hopper.xml"
    n_frames = 4
    default_physics = Physics(solver="newton", iterations=1, ls_iterations=4,
                              euler_damping=False)
    ctrl_cost_weight = 1e-3
    healthy_reward = 1.0
    reset_noise_scale = 5e-3

    def observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        z = _TORSO_Z0 + qpos[1:2]
        return jnp.concatenate([z, qpos[2:], jnp.clip(qvel, -10.0, 10.0)])

    def is_healthy(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        state = jnp.concatenate([qpos[2:], qvel])
        in_range = jnp.all((-_MAX_STATE < state) & (state < _MAX_STATE))
        z, angle = _TORSO_Z0 + qpos[1], qpos[2]
        return in_range & (z > _MIN_Z) & (jnp.abs(angle) < _MAX_ANGLE)

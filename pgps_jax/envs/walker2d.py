"""Walker2d: Gym `Walker2d-v4` on Brax's `walker2d.xml`, stepped on MJX.

Brax's model drops the `ref` of the rootz joint, so the torso height is z = 1.25 + qpos[1]
(Gym's qpos[1] is the height itself), and integrates with Euler where Gym's asks for RK4.

- Observation (17): z, qpos[2:] (torso angle, six joint angles), then clip(qvel, −10, 10)
  (9).
- Action (6): right then left thigh, leg, foot torques in [-1, 1].
- Reward: 1.0·Δx/dt + 1.0 (healthy, paid every step) − 1e-3·Σa², x = qpos[0] (rootx).
- Termination: unless 0.8 < z < 2.0 and |torso angle qpos[2]| < 1.0.
- dt: 0.002 s timestep × frame_skip 4 = 0.008 s.
- Reset: qpos0 + U(±5e-3), qvel = U(±5e-3).
- Physics: Newton, 3 iterations, 4 line-search iterations, Euler damping off: the fewest
  iterations that carry the PGPS authors' trained walker as the model's converged solve
  does (100 episodes: 5,739 and 4 falls against 5,768 and 3; with 1 iteration 3,823 and 60
  falls, with 2 5,529 and 13; BENCHMARKS.md, "The physics of the other tasks").
"""

import jax
import jax.numpy as jnp

from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.physics import Physics

_TORSO_Z0 = 1.25
_HEALTHY_Z = (0.8, 2.0)
_MAX_ANGLE = 1.0


class Walker2d(MjxEnv):
    """Walker2d-v4; see the module docstring for its terms."""

    xml = "walker2d.xml"
    n_frames = 4
    default_physics = Physics(solver="newton", iterations=3, ls_iterations=4,
                              euler_damping=False)
    ctrl_cost_weight = 1e-3
    healthy_reward = 1.0
    reset_noise_scale = 5e-3

    def observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        z = _TORSO_Z0 + qpos[1:2]
        return jnp.concatenate([z, qpos[2:], jnp.clip(qvel, -10.0, 10.0)])

    def is_healthy(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        z, angle = _TORSO_Z0 + qpos[1], qpos[2]
        return (_HEALTHY_Z[0] < z) & (z < _HEALTHY_Z[1]) & (jnp.abs(angle) < _MAX_ANGLE)

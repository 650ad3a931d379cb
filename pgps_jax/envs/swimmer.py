"""Swimmer: Gym `Swimmer-v4` on Brax's `swimmer.xml`, stepped on MJX.

Brax's own swimmer env refuses the MJX backend; MJX itself runs the model, including its
viscous fluid forces (density 4000, viscosity 0.1).

- Observation (8): qpos[2:] (body angle, two joint angles) then qvel (5), unclipped.
- Action (2): torques of rot2, rot3 in [-1, 1].
- Reward: 1.0·Δx/dt − 1e-4·Σa², x = qpos[0] (slider1).
- Termination: none.
- dt: 0.01 s timestep × frame_skip 4 = 0.04 s.
- Reset: qpos0 + U(±0.1), qvel = U(±0.1).
- Physics: Newton, 1 iteration, 4 line-search iterations (the model has no damped joint and
  no contact). Mean return against the model's own settings: sinusoids +3%; random actions
  return about 0 under both (BENCHMARKS.md).
"""

import jax
import jax.numpy as jnp

from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.physics import Physics


class Swimmer(MjxEnv):
    """Swimmer-v4; see the module docstring for its terms."""

    xml = "swimmer.xml"
    n_frames = 4
    default_physics = Physics(solver="newton", iterations=1, ls_iterations=4,
                              euler_damping=False)
    ctrl_cost_weight = 1e-4
    reset_noise_scale = 0.1

    def observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return jnp.concatenate([qpos[2:], qvel])

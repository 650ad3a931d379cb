"""HalfCheetah: Gym `HalfCheetah-v4` on Brax's `half_cheetah.xml`, stepped on MJX.

- Observation (17): qpos[1:] (rootz, rooty, six joint angles) then qvel (9), unclipped.
- Action (6): torques of bthigh, bshin, bfoot, fthigh, fshin, ffoot in [-1, 1].
- Reward: 1.0·Δx/dt − 0.1·Σa², x = qpos[0] (rootx).
- Termination: none.
- dt: 0.01 s timestep × frame_skip 5 = 0.05 s.
- Reset: qpos0 + U(±0.1), qvel = 0.1·N(0, 1).
- Physics: Newton, 3 iterations, 4 line-search iterations, Euler damping off: the fewest
  iterations that carry the PGPS authors' trained runner within 5% of the model's converged
  solve (100 episodes: 11,605 against 11,991; with 1 iteration 7,790, with 2 11,224;
  BENCHMARKS.md, "The physics of the other tasks").
"""

import jax
import jax.numpy as jnp

from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.physics import Physics


class HalfCheetah(MjxEnv):
    """HalfCheetah-v4; see the module docstring for its terms."""

    xml = "half_cheetah.xml"
    n_frames = 5
    default_physics = Physics(solver="newton", iterations=3, ls_iterations=4,
                              euler_damping=False)
    ctrl_cost_weight = 0.1
    reset_noise_scale = 0.1
    qvel_noise_normal = True

    def observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return jnp.concatenate([qpos[1:], qvel])

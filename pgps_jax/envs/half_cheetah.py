"""HalfCheetah: Gym `HalfCheetah-v4` on Brax's `half_cheetah.xml`, stepped on MJX.

- Observation (17): qpos[1:] (rootz, rooty, six joint angles) then qvel (9), unclipped.
- Action (6): torques of bthigh, bshin, bfoot, fthigh, fshin, ffoot in [-1, 1].
- Reward: 1.0·Δx/dt − 0.1·Σa², x = qpos[0] (rootx).
- Termination: none.
- dt: 0.01 s timestep × frame_skip 5 = 0.05 s.
- Reset: qpos0 + U(±0.1), qvel = 0.1·N(0, 1).
- Physics: Newton, 1 iteration, 4 line-search iterations, Euler damping off (with it on,
  one iteration goes non-finite). Mean return against the model's own settings: random
  actions +13% (less backward drift), sinusoids −4%; `iterations=2` comes within 6% at
  1.4× the step time (BENCHMARKS.md).
"""

import jax
import jax.numpy as jnp

from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.physics import Physics


class HalfCheetah(MjxEnv):
    """HalfCheetah-v4; see the module docstring for its terms."""

    xml = "half_cheetah.xml"
    n_frames = 5
    default_physics = Physics(solver="newton", iterations=1, ls_iterations=4,
                              euler_damping=False)
    ctrl_cost_weight = 0.1
    reset_noise_scale = 0.1
    qvel_noise_normal = True

    def _observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return jnp.concatenate([qpos[1:], qvel])

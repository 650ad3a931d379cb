"""Ant: Gym `Ant-v4` (contact forces excluded, its default) on Brax's `ant.xml`, on MJX.

Brax's model lets only the four feet touch the floor (Gym's: every geom).

- Observation (27): qpos[2:] (torso z, torso quaternion, eight joint angles) then qvel (14),
  unclipped.
- Action (8): hip and ankle torques in [-1, 1].
- Reward: 1.0·Δx/dt + 1.0 (healthy, paid every step) − 0.5·Σa², x = qpos[0] (the torso's
  x, as Gym's `get_body_com("torso")`). No contact cost (Gym v4's default).
- Termination: unless 0.2 ≤ torso z ≤ 1.0 (Gym also ends on a non-finite state, which the
  NaN guard covers).
- dt: 0.01 s timestep × frame_skip 5 = 0.05 s.
- Reset: init_qpos + U(±0.1), qvel = 0.1·N(0, 1). init_qpos is the model's own (torso at
  0.55 m, legs bent inside their joint ranges); Gym starts from qpos0 (torso at 0.75 m, legs
  straight, ankles outside their ranges).
- Physics: Newton, 1 iteration, 4 line-search iterations, Euler damping off, as Brax's ant
  on MJX. Mean return against the model's own settings: random actions +7 ± 9%, sinusoids
  +15 ± 6% (BENCHMARKS.md).
"""

import jax
import jax.numpy as jnp

from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.envs.physics import Physics

_HEALTHY_Z = (0.2, 1.0)


class Ant(MjxEnv):
    """Ant-v4; see the module docstring for its terms."""

    xml = "ant.xml"
    n_frames = 5
    default_physics = Physics(solver="newton", iterations=1, ls_iterations=4,
                              euler_damping=False)
    ctrl_cost_weight = 0.5
    healthy_reward = 1.0
    reset_noise_scale = 0.1
    qvel_noise_normal = True

    def _observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return jnp.concatenate([qpos[2:], qvel])

    def is_healthy(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return (_HEALTHY_Z[0] <= qpos[2]) & (qpos[2] <= _HEALTHY_Z[1])

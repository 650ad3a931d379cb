"""Ant: Gym `Ant-v4` (contact forces excluded, its default) on Brax's `ant.xml`, on MJX.

The model is made Gym's: every geom touches the floor with Gym's 0.01 m margin (Brax's lets
four added foot spheres only), integrated with Gym's RK4.

- Observation (27): qpos[2:] (torso z, torso quaternion, eight joint angles) then qvel (14),
  unclipped.
- Action (8): hip and ankle torques in [-1, 1].
- Reward: 1.0·Δx/dt + 1.0 (healthy, paid every step) − 0.5·Σa², x = qpos[0] (the torso's
  x, as Gym's `get_body_com("torso")`). No contact cost (Gym v4's default).
- Termination: unless 0.2 ≤ torso z ≤ 1.0 (Gym also ends on a non-finite state, which the
  NaN guard covers).
- dt: 0.01 s timestep × frame_skip 5 = 0.05 s.
- Reset: qpos0 + U(±0.1), qvel = 0.1·N(0, 1), as Gym (torso at 0.75 m, legs straight,
  ankles outside their ranges).
- Physics: RK4, Newton with 3 iterations and 2 line-search iterations. Brax's settings
  (Euler, feet-only contacts, 1 iteration) throw a walking ant above the healthy range:
  the authors' published Ant-v2 actor ends its episodes within 10–80 steps there, and
  walks here at 5,366 (100 episodes, 8 ended early) against 5,629 (2 ended) on the model
  solved to convergence; with 2 iterations 4,631 (24 ended), with 5 no better than 3; with
  4 line-search iterations 5,346 (13 ended) at a fifth more operations per step, with 1
  5,437 (5 ended) but a line search that the GPU's loop rewrites cannot write out
  (BENCHMARKS.md, "The ant's physics" and "The physics of the other tasks").
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
    default_physics = Physics(integrator="rk4", solver="newton", iterations=3,
                              ls_iterations=2, floor_contacts="gym")
    ctrl_cost_weight = 0.5
    healthy_reward = 1.0
    reset_noise_scale = 0.1
    qvel_noise_normal = True

    def observation(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return jnp.concatenate([qpos[2:], qvel])

    def is_healthy(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return (_HEALTHY_Z[0] <= qpos[2]) & (qpos[2] <= _HEALTHY_Z[1])

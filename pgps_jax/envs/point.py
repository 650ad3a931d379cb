"""A tiny, fast point-mass task for tests and examples.

A point in the plane is pushed by a bounded force toward a fixed goal. It is not a MuJoCo
task; it exists so the whole algorithm can be exercised in seconds on a CPU.

- Observation (4): position (x, y) and velocity (vx, vy).
- Action (2): force in [-1, 1]², velocity ← 0.8·velocity + 0.2·action, position += dt·velocity.
- Reward: 1 − ‖position − goal‖ per step (goal = (1, 0.5)).
- Termination: leaving the box ‖position‖_∞ > 2 (terminal, as an unhealthy MuJoCo state).
- Reset: position and velocity uniform in [−0.1, 0.1].
"""

from brax.envs.base import Env, State
import jax
import jax.numpy as jnp
import numpy as np

_GOAL = np.array([1.0, 0.5], np.float32)  # numpy: importing starts no JAX backend
_BOX = 2.0


class PointMass(Env):
    """Point mass steered toward a goal; see the module docstring for its terms."""

    def __init__(self, dt: float = 0.1):
        self._dt = dt

    def reset(self, rng: jax.Array) -> State:
        obs = jax.random.uniform(rng, (4,), minval=-0.1, maxval=0.1)
        zero = jnp.zeros(())
        return State(pipeline_state=None, obs=obs, reward=zero, done=zero,
                     metrics={"unstable": zero}, info={})

    def step(self, state: State, action: jax.Array) -> State:
        position, velocity = state.obs[:2], state.obs[2:]
        velocity = 0.8 * velocity + 0.2 * jnp.clip(action, -1.0, 1.0)
        position = position + self._dt * velocity
        reward = 1.0 - jnp.linalg.norm(position - _GOAL)
        done = (jnp.max(jnp.abs(position)) > _BOX).astype(jnp.float32)
        return state.replace(obs=jnp.concatenate([position, velocity]), reward=reward, done=done)

    @property
    def observation_size(self) -> int:
        return 4

    @property
    def action_size(self) -> int:
        return 2

    @property
    def backend(self) -> str:
        return "jax"

"""The PGPS authors' published actors played on our envs: a check of the envs against Gym's.

The authors publish one trained actor per task (github.com/NamKim88/PGPS,
`learned_models/<Task>-v2.npy`: the flat parameters of their 400-300 ELU actor with a tanh
output, in PyTorch's order, trained on Gym's v2 tasks under mujoco-py 2.0). An actor plays
about as well on our env as on Gym's when the two agree on observation, action, reward and
physics; a gait tuned to Gym's physics that falls or jumps out of the healthy range here
points at a difference in the physics.

`--engine c` plays the same episodes (start states from the same keys, the same observation,
reward and termination) in MuJoCo's C engine (`mujoco.mj_step`) on the env's model and
settings, where the solver stops at its tolerance: with `--env iterations=100
ls_iterations=50 euler_damping=true` that is the model's physics solved to convergence, the
reference that a truncated MJX solve is measured against.

Gym's Ant-v2 observation has 84 more entries than ours (`cfrc_ext`, zero under mujoco-py 2.0,
openai/gym#1541); the weights that read them are dropped. Each record of `--out` (a JSON list,
appended to) holds, per task, the returns and lengths of `--episodes` deterministic episodes
of 1000 steps from PRNGKey(0)'s start states, and the physics they ran on.

    git clone https://github.com/NamKim88/PGPS
    python -m benchmarks.authors_actors --models PGPS/learned_models
    python -m benchmarks.authors_actors --models PGPS/learned_models --tasks ant \\
        --env integrator=euler iterations=1 floor_contacts=model start_pose=init_qpos
    python -m benchmarks.authors_actors --models PGPS/learned_models --engine c \\
        --env iterations=100 ls_iterations=50 euler_damping=true
"""

import argparse
import json
import os
import pathlib
from typing import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from benchmarks.timing import provenance
from pgps_jax.agent.rollout import run_episodes
from pgps_jax.cli.assignments import env_assignments
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import TASKS, make_env

GYM_NAMES = {"halfcheetah": "HalfCheetah-v2", "hopper": "Hopper-v2",
             "walker2d": "Walker2d-v2", "ant": "Ant-v2", "swimmer": "Swimmer-v2"}
HIDDEN = (400, 300)
EPISODE_STEPS = 1000


def load_actor(path: pathlib.Path, obs_size: int, action_size: int) -> dict:
    """The layers of a flat PyTorch actor vector (weights [out, in], then biases, layer by
    layer); the first layer keeps the weights of our `obs_size` observation entries."""
    flat = np.load(path).astype(np.float32)
    gym_obs = (flat.size - HIDDEN[0] - HIDDEN[1] * (HIDDEN[0] + 1)
               - action_size * (HIDDEN[1] + 1)) // HIDDEN[0]
    sizes = (gym_obs, *HIDDEN, action_size)
    layers, start = [], 0
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
        w = flat[start:start + fan_out * fan_in].reshape(fan_out, fan_in)
        b = flat[start + fan_out * fan_in:start + fan_out * (fan_in + 1)]
        layers.append((jnp.asarray(w), jnp.asarray(b)))
        start += fan_out * (fan_in + 1)
    if start != flat.size or gym_obs < obs_size:
        raise ValueError(f"{path}: {flat.size} parameters do not make a {sizes} actor "
                         f"for an observation of {obs_size}")
    (w1, b1), *rest = layers
    return {"layers": [(w1[:, :obs_size], b1), *rest]}


def act(params: dict, obs: jax.Array) -> jax.Array:
    """ELU hidden layers, tanh output (the authors' default actor)."""
    *hidden, (w_out, b_out) = params["layers"]
    for w, b in hidden:
        obs = jax.nn.elu(w @ obs + b)
    return jnp.tanh(w_out @ obs + b_out)


def play(task: str, models: pathlib.Path, episodes: int, env_kwargs: dict,
         engine: str = "mjx", steps: int = EPISODE_STEPS) -> dict:
    """`episodes` deterministic episodes of up to `steps` env steps of the authors' actor for
    `task`, from PRNGKey(0)'s start states, stepped by MJX or by MuJoCo's C engine; with the
    physics they ran on (`MjxEnv.settings`)."""
    env = make_env(task, **env_kwargs)
    params = load_actor(models / f"{GYM_NAMES[task]}.npy", env.observation_size,
                        env.action_size)
    keys = jax.random.split(jax.random.PRNGKey(0), episodes)
    if engine == "c":
        episode = c_episodes(env, params)
        returns, lengths = np.array([episode(key, steps) for key in keys]).T
    else:
        batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (episodes, *x.shape)), params)
        limits = jnp.full((episodes,), steps, jnp.int32)
        out = jax.jit(lambda p, k: run_episodes(env, act, p, k, limits, steps,
                                                record=False))(batch, keys)
        returns, lengths = np.asarray(out.returns), np.asarray(out.lengths)
    return {"returns": np.round(returns, 1).tolist(), "lengths": lengths.astype(int).tolist(),
            "mean": float(returns.mean()), "std": float(returns.std()),
            "physics": env.settings()}


def c_episodes(env, params: dict) -> Callable[[jax.Array, int], tuple[float, int]]:
    """A function of (key, steps) that plays one episode with the env's model stepped by
    `mujoco.mj_step` (`n_frames` steps per env step) from the env's reset state for `key`,
    and returns its return and length. As on MJX, the action is clipped, the episode ends
    after a step that leaves the healthy range, and a step whose physics fails (a non-finite
    state, or one MuJoCo had to reset) ends it without its reward."""
    model = env.mj_model
    policy = jax.jit(lambda obs: act(params, obs))
    observe, healthy = jax.jit(env.observation), jax.jit(env.is_healthy)
    reward = jax.jit(lambda q0, q1, a: env.reward(env.reward_terms(q0, q1, a)))
    resets = [mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL,
              mujoco.mjtWarning.mjWARN_BADQACC]  # MuJoCo reset a state it could not step

    def episode(key: jax.Array, steps: int) -> tuple[float, int]:
        data = mujoco.MjData(model)
        start = env.reset(key).pipeline_state
        data.qpos[:], data.qvel[:] = np.asarray(start.qpos), np.asarray(start.qvel)
        total, length = 0.0, 0
        while length < steps:
            action = np.clip(np.asarray(policy(observe(data.qpos, data.qvel))), -1.0, 1.0)
            qpos0 = data.qpos.copy()
            data.ctrl[:] = action
            for _ in range(env.n_frames):
                mujoco.mj_step(model, data)
            length += 1
            if any(data.warning[w].number for w in resets) or not (
                    np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()):
                break
            total += float(reward(qpos0, data.qpos, action))
            if not healthy(data.qpos, data.qvel):
                break
        return total, length
    return episode


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", type=pathlib.Path, required=True,
                        help="the authors' learned_models directory")
    parser.add_argument("--tasks", nargs="+", choices=TASKS, default=list(TASKS))
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--env", nargs="*", default=[], action="extend", metavar="NAME=VALUE",
                        help="make_env keyword arguments for every task")
    parser.add_argument("--engine", choices=("mjx", "c"), default="mjx",
                        help="step the physics with MJX (the envs' own) or MuJoCo's C engine")
    parser.add_argument("--out", default="benchmarks/results/authors_actors.json")
    args = parser.parse_args()
    try:
        env_kwargs = env_assignments(args.env)
    except UsageError as e:
        parser.error(str(e))
    record = {**provenance(), "engine": args.engine, "env": env_kwargs,
              "episodes": args.episodes, "tasks": {}}
    for task in args.tasks:
        record["tasks"][task] = play(task, args.models, args.episodes, env_kwargs, args.engine)
        result = record["tasks"][task]
        print(f"{task:12s} {args.engine} {env_kwargs or 'defaults'}: {result['mean']:8.0f} ± "
              f"{result['std']:5.0f}, lengths {min(result['lengths'])}–"
              f"{max(result['lengths'])}", flush=True)
    records = json.loads(open(args.out).read()) if os.path.exists(args.out) else []
    with open(args.out, "w") as f:
        json.dump(records + [record], f, indent=1)


if __name__ == "__main__":
    main()

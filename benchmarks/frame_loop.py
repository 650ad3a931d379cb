"""An env step's frames in a device loop or unrolled: rollout cost at batch 10 and 40.

halfcheetah, 1000-step episodes of CEM-sampled actors via `rollout.run_episodes`; the same
code with `physics.step_frames` as a rolled `fori_loop` (the form before it was unrolled) and
as it is now. Milliseconds per env step (median of 3) and compile seconds.

    python benchmarks/frame_loop.py benchmarks/results/frame_loop.json
"""
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax import cem
from pgps_jax.config import for_task
from pgps_jax.envs import make_env, physics
from pgps_jax.pgps import PGPS
from pgps_jax.rollout import run_episodes

T = int(os.environ.get("T", 1000))      # T=5: a quick CPU check of the script
out = {}
config = for_task("halfcheetah")
unrolled_step_frames = physics.step_frames
for unroll in (False, True):
    physics.step_frames = unrolled_step_frames if unroll else (
        lambda m, d, n: jax.lax.fori_loop(0, n, lambda _, x: physics.mjx.step(m, x), d))
    env = make_env("halfcheetah")
    agent = PGPS(config, env)
    policy = agent.policy
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    for batch in (10, 40):
        key = jax.random.PRNGKey(batch)
        pop = cem.ask(key, state.cem, batch)
        keys = jax.random.split(key, batch)
        fn = jax.jit(lambda p, k: run_episodes(env, policy, p, k, jnp.full((batch,), T), T).returns)
        t = time.perf_counter(); c = fn.lower(pop, keys).compile(); comp = time.perf_counter() - t
        jax.block_until_ready(c(pop, keys))
        ts = []
        for _ in range(3):
            t = time.perf_counter(); jax.block_until_ready(c(pop, keys)); ts.append(time.perf_counter() - t)
        name = f"b{batch}_{'unrolled' if unroll else 'rolled'}"
        out[name] = {"ms_per_step": float(np.median(ts)) / T * 1e3, "compile_s": comp}
        print(name, out[name], flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)

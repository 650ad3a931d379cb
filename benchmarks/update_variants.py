"""TD3 update variants in the update loop: per-update time and compiled kernel counts.

halfcheetah sizes, batch 256, 2000 updates in `td3.repeat` loops (unroll 4 and 8), with the
project's optimiser and with it wrapped in `optax.flatten` (one flat vector):
  critic_v0: the target action π'(s') + noise computed inside every update;
  critic_v1: target actions of all updates computed before the loop (what `td3.train` does);
  actor_a0:  the elite's actions computed inside every update;
  actor_a1:  the elite's actions given (precomputed, as `td3.train` does).
Kernel counts are fusions, custom calls and copies in the compiled program (all unrolled
copies of the loop body).

    python benchmarks/update_variants.py benchmarks/results/update_variants.json
"""
import json
import os
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from pgps_jax import buffer as replay
from pgps_jax.pgps import PGPS
from pgps_jax.config import for_task
from pgps_jax.envs import make_env
from pgps_jax.td3 import TD3, repeat

U = int(os.environ.get("U", 2000))     # U=8: a quick CPU check of the script
env = make_env("halfcheetah")
config = for_task("halfcheetah")
state = jax.jit(PGPS(config, env).init)(jax.random.PRNGKey(0))
A = env.action_size
out = {}



class FlatTD3(TD3):
    def _optimizer(self, lr):
        return optax.flatten(super()._optimizer(lr))



def kernels(compiled):
    txt = compiled.as_text()
    return {"fusion": len(re.findall(r"= \S+ fusion\(", txt)),
            "custom_call": len(re.findall(r"custom-call\(", txt)),
            "copy": len(re.findall(r"= \S+ copy\(", txt))}



def bench(name, fn, *args):
    c = jax.jit(fn).lower(*args).compile()
    jax.block_until_ready(c(*args))
    ts = []
    for _ in range(3):
        t = time.perf_counter(); jax.block_until_ready(c(*args)); ts.append(time.perf_counter() - t)
    out[name] = {"us_per_update": float(np.median(ts)) / U * 1e6, **kernels(c)}
    print(name, out[name], flush=True)

key = jax.random.PRNGKey(1)
rows = replay.random_rows(state.buffer, key, (U, 256))
for unroll in (4, 8):
  for flat in (False, True):
    td3 = (FlatTD3 if flat else TD3)(config, env.observation_size, A)
    ts = td3.init(key)
    if flat:
        ts = ts.replace(actor_opt=td3.actor_optimizer.init(ts.actor),
                        critic_opt=td3.critic_optimizer.init(ts.critic))
    noise = td3.smoothing_noise(key, (U, 256, A))

    def critic_v0(ts, buf, n):
        def body(i, t):
            batch = replay.gather(buf, rows[i])
            return td3.critic_update(t, batch, td3.target_actions(t.actor_target, batch.next_obs,
                                                                  noise[i]))[0]
        return repeat(n, body, ts, unroll)

    def critic_v1(ts, buf, n):
        next_actions = td3.target_actions(ts.actor_target, buf.data.next_obs[rows], noise)
        def body(i, t):
            return td3.critic_update(t, replay.gather(buf, rows[i]), next_actions[i])[0]
        return repeat(n, body, ts, unroll)

    def actor_a0(ts, buf, n, elite):
        def body(i, t):
            obs = buf.data.obs[rows[i]]
            return td3.actor_update(t, obs, td3.actor_net.apply(elite, obs), jnp.asarray(0.0))[0]
        return repeat(n, body, ts, unroll)

    def actor_a1(ts, buf, n, elite):
        zeros = jnp.zeros((256, A))
        def body(i, t):
            obs = buf.data.obs[rows[i]]
            return td3.actor_update(t, obs, zeros, jnp.asarray(0.0))[0]
        return repeat(n, body, ts, unroll)

    n = jnp.asarray(U)
    tag = f"u{unroll}{'_flat' if flat else ''}"
    bench(f"critic_v0_{tag}", critic_v0, ts, state.buffer, n)
    bench(f"critic_v1_{tag}", critic_v1, ts, state.buffer, n)
    bench(f"actor_a0_{tag}", actor_a0, ts, state.buffer, n, ts.actor)
    bench(f"actor_a1_{tag}", actor_a1, ts, state.buffer, n, ts.actor)
json.dump(out, open(sys.argv[1], "w"), indent=1)

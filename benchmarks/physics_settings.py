"""Evidence for each task's solver settings: stability, and returns against the model's own.

Per task, four settings step the same start states under the same action sequences:
- the env's defaults (Newton, 1 iteration, 4 line-search iterations, Euler damping off)
  and the same with Euler damping on, each for `--steps` steps;
- the settings written in Brax's model (`physics.model_defaults`: Newton, 4 iterations
  (swimmer 8), 50 line-search iterations, Euler damping on) and the same with Euler damping
  off, each until every episode has ended (at most 1000 steps).
Half of the envs take uniform random actions, half fixed sinusoids (per env a frequency in
0.5–3 Hz, per joint a phase). Past a termination the physics keeps stepping, so the
stability check also covers fallen, flailing bodies. Where the model has no damped joint,
the Euler-damping variants are the same physics and are left out.

Reported per task and settings: non-finite physics steps (`metrics["unstable"]`) over all
steps and envs; the mean (and standard error) of the episode return (1000 steps or up to the
first termination) for random and for sinusoidal actions; and for each settings the mean
per-env difference from the model's settings relative to the model's mean, with the standard
error of that paired difference.

    python benchmarks/physics_settings.py --envs 512 --steps 10000
"""

import argparse
import concurrent.futures
import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax.envs import TASKS, make_env
from pgps_jax.envs.physics import model_defaults

EPISODE = 1000


def action_fn(key: jax.Array, n_envs: int, action_size: int, dt: float):
    """Returns a(t) -> (2·n_envs, action_size): n_envs random rows, then n_envs sinusoids."""
    key_freq, key_phase, key_random = jax.random.split(key, 3)
    freq = jax.random.uniform(key_freq, (n_envs, 1), minval=0.5, maxval=3.0)
    phase = jax.random.uniform(key_phase, (n_envs, action_size), maxval=2 * jnp.pi)

    def actions(t):
        random = jax.random.uniform(jax.random.fold_in(key_random, t), (n_envs, action_size),
                                    minval=-1.0, maxval=1.0)
        return jnp.concatenate([random, jnp.sin(2 * jnp.pi * freq * dt * t + phase)])
    return actions


def make_evidence_run(env, n_envs: int):
    """(key, n_steps, min_steps) -> per-env episode return, length, unstable-step count.

    Steps at most `n_steps`, and stops after `min_steps` once every episode has ended.
    """
    def run(key, n_steps, min_steps):
        key_reset, key_actions = jax.random.split(key)
        state = jax.vmap(env.reset)(jax.random.split(key_reset, 2 * n_envs))
        actions = action_fn(key_actions, n_envs, env.action_size, env.dt)
        zeros = jnp.zeros(2 * n_envs)

        def cond(carry):
            t, _, alive, *_ = carry
            return (t < n_steps) & ((t < min_steps) | (jnp.any(alive > 0) & (t < EPISODE)))

        def body(carry):
            t, state, alive, ret, length, unstable = carry
            state = jax.vmap(env.step)(state, actions(t))
            counted = alive * (t < EPISODE)
            alive = alive * (1.0 - state.done)
            return (t + 1, state, alive, ret + counted * state.reward, length + counted,
                    unstable + state.metrics["unstable"])

        carry = (jnp.int32(0), state, jnp.ones(2 * n_envs), zeros, zeros, zeros)
        t, _, _, ret, length, unstable = jax.lax.while_loop(cond, body, carry)
        return t, ret, length, unstable
    return jax.jit(run)


def candidates(task: str, n_steps: int) -> dict[str, tuple[dict, int, int]]:
    """Name -> (settings overrides, max steps, min steps) for one task."""
    env = make_env(task)
    model = dataclasses.asdict(model_defaults(env.xml))
    runs = {"env_default": ({}, n_steps, n_steps), "model": (model, EPISODE, 0)}
    if env.mj_model.dof_damping.any():
        flipped = not env.physics.euler_damping
        runs["env_default_euler_damping_" + ("on" if flipped else "off")] = (
            {"euler_damping": flipped}, n_steps, n_steps)
        runs["model_euler_damping_off"] = ({**model, "euler_damping": False}, EPISODE, 0)
    return runs


def summarise(env, ret, length, unstable, steps, seconds, n_envs) -> dict:
    """Figures of one run (arrays over 2·n_envs envs: random rows, then sinusoid rows)."""
    out = {"settings": dataclasses.asdict(env.physics), "steps": steps, "envs": 2 * n_envs,
           "unstable_steps": int(unstable.sum()),
           "envs_with_unstable_steps": int((unstable > 0).sum()),
           "ms_per_step": 1e3 * seconds / steps}
    for name, rows in (("random", slice(0, n_envs)), ("sinusoid", slice(n_envs, None))):
        out[f"{name}_return_mean"] = float(ret[rows].mean())
        out[f"{name}_return_sem"] = float(ret[rows].std() / np.sqrt(n_envs))
        out[f"{name}_length_mean"] = float(length[rows].mean())
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--envs", type=int, default=512, help="envs per kind of action")
    parser.add_argument("--steps", type=int, default=10_000,
                        help="steps of the settings checked for stability")
    parser.add_argument("--out", default="benchmarks/results/physics_settings.json")
    args = parser.parse_args()
    key = jax.random.PRNGKey(0)

    def build(task, name, settings, n_steps, min_steps):
        env = make_env(task, **settings)
        compiled = make_evidence_run(env, args.envs).lower(key, 0, 0).compile()
        return name, env, compiled, n_steps, min_steps

    results = {"device": jax.devices()[0].device_kind, "episode": EPISODE,
               "envs_per_action_kind": args.envs, "tasks": {}}
    start = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        # Compile everything in the background; run each task as soon as its runs compiled.
        futures = {task: [pool.submit(build, task, name, *spec)
                          for name, spec in candidates(task, args.steps).items()]
                   for task in args.tasks.split(",")}
        for task, task_futures in futures.items():
            runs = [f.result() for f in task_futures]
            print(f"{task}: compiled after {time.perf_counter() - start:.0f} s", flush=True)
            results["tasks"][task] = run_task(task, runs, key, args.envs)
            with open(args.out, "w") as f:
                json.dump(results, f, indent=1)


def run_task(task: str, runs, key: jax.Array, n_envs: int) -> dict:
    """Runs one task's compiled settings and compares each with the model's settings."""
    out, returns = {}, {}
    for name, env, compiled, n_steps, min_steps in runs:
        start = time.perf_counter()
        t, ret, length, unstable = map(np.asarray, compiled(key, n_steps, min_steps))
        seconds = time.perf_counter() - start
        returns[name] = ret
        res = out[name] = summarise(env, ret, length, unstable, int(t), seconds, n_envs)
        print(f"{task:12s} {name:34s} steps {int(t):6d} unstable {res['unstable_steps']:5d}"
              f" | random {res['random_return_mean']:9.2f} ±{res['random_return_sem']:6.2f}"
              f" | sinusoid {res['sinusoid_return_mean']:9.2f} ±{res['sinusoid_return_sem']:6.2f}"
              f" | {res['ms_per_step']:6.2f} ms/step", flush=True)
    for name, ret in returns.items():
        ref, res = returns["model"], out[name]
        for kind, rows in (("random", slice(0, n_envs)), ("sinusoid", slice(n_envs, None))):
            diff, scale = ret[rows] - ref[rows], abs(ref[rows].mean())
            res[f"{kind}_vs_model"] = float(diff.mean() / scale)
            res[f"{kind}_vs_model_sem"] = float(diff.std() / np.sqrt(n_envs) / scale)
        print(f"{task:12s} {name:34s} vs model: random {100 * res['random_vs_model']:+6.1f}%"
              f" ±{100 * res['random_vs_model_sem']:.1f} | sinusoid"
              f" {100 * res['sinusoid_vs_model']:+6.1f}% ±{100 * res['sinusoid_vs_model_sem']:.1f}",
              flush=True)
    return out


if __name__ == "__main__":
    main()

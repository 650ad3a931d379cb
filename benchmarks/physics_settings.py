"""Evidence for each task's solver settings: stability, and returns against the model's own.

Per task, several solver settings step the same start states under the same actions:
- `env_default`, the env's settings, for `--steps` steps (the stability check);
- `model`, the settings written in Brax's model (`physics.model_defaults`: Newton,
  4 iterations (swimmer 8), 50 line-search iterations, Euler damping on), and, where the
  model has damped joints, `model_euler_damping_off`, each until every first episode has
  ended (at most 1000 steps); `--no-reference` leaves them out;
- each of `--extra` ("solver:iterations:ls_iterations:on|off") for `--extra-steps`.
Half of the envs take uniform random actions, half fixed sinusoids: env i, joint j gets
sin(2π·f_i·dt·t − j·lag_i), f_i ~ U(0.5, 3) Hz, lag_i ~ U(0.5, 1.5) rad, a travelling wave
along the actuators. As in training, an episode restarts from a fresh reset when it
terminates (or goes non-finite) and after 1000 steps.

Reported per task and settings: non-finite steps (`metrics["unstable"]`) over all steps and
envs; episodes run; the mean (and standard error) of the first episode's return and length
for random and for sinusoidal actions; and the mean per-env difference of that return from
the model's settings, relative to the model's mean, with the standard error of the paired
difference.

    python -m benchmarks.physics_settings --steps 1000 --extra newton:2:4:off,newton:1:4:on \
        --out benchmarks/results/physics_settings_sweep.json
    python -m benchmarks.physics_settings --steps 10000 --no-reference \
        --out benchmarks/results/physics_settings_stability.json
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
    """Returns a(t) -> (2·n_envs, action_size): n_envs random rows, then n_envs sinusoids.

    Sinusoid of env i, joint j: sin(2π·f_i·dt·t − j·lag_i), f_i ~ U(0.5, 3) Hz and
    lag_i ~ U(0.5, 1.5) rad: a travelling wave along the actuators, fixed per env.
    """
    key_freq, key_lag, key_random = jax.random.split(key, 3)
    freq = jax.random.uniform(key_freq, (n_envs, 1), minval=0.5, maxval=3.0)
    lag = jax.random.uniform(key_lag, (n_envs, 1), minval=0.5, maxval=1.5)
    phase = -lag * jnp.arange(action_size)

    def actions(t):
        random = jax.random.uniform(jax.random.fold_in(key_random, t), (n_envs, action_size),
                                    minval=-1.0, maxval=1.0)
        return jnp.concatenate([random, jnp.sin(2 * jnp.pi * freq * dt * t + phase)])
    return actions


def make_evidence_run(env, n_envs: int):
    """(key, n_steps, min_steps) -> steps run and, per env, first-episode return and length,
    episodes ended and unstable steps.

    Episodes restart from a fresh reset on termination and after 1000 steps, as in training.
    Steps at most `n_steps`; after `min_steps`, stops once every first episode has ended.
    """
    def run(key, n_steps, min_steps):
        key_reset, key_actions, key_restart = jax.random.split(key, 3)
        reset = jax.vmap(env.reset)
        state = reset(jax.random.split(key_reset, 2 * n_envs))
        actions = action_fn(key_actions, n_envs, env.action_size, env.dt)
        zeros = jnp.zeros(2 * n_envs)

        def cond(carry):
            t, _, _, alive, *_ = carry
            return (t < n_steps) & ((t < min_steps) | (jnp.any(alive > 0) & (t < EPISODE)))

        def body(carry):
            t, state, age, alive, ret, length, episodes, unstable = carry
            state = jax.vmap(env.step)(state, actions(t))
            counted = alive * (t < EPISODE)
            ret, length = ret + counted * state.reward, length + counted
            alive = alive * (1.0 - state.done)
            unstable = unstable + state.metrics["unstable"]
            age = age + 1
            restart = (state.done > 0) | (age >= EPISODE)
            fresh = reset(jax.random.split(jax.random.fold_in(key_restart, t), 2 * n_envs))
            state = jax.tree.map(
                lambda new, old: jnp.where(restart.reshape((-1,) + (1,) * (old.ndim - 1)),
                                           new, old), fresh, state)
            return (t + 1, state, jnp.where(restart, 0, age), alive, ret, length,
                    episodes + restart, unstable)

        carry = (jnp.int32(0), state, jnp.zeros(2 * n_envs, jnp.int32), jnp.ones(2 * n_envs),
                 zeros, zeros, zeros, zeros)
        t, _, _, _, ret, length, episodes, unstable = jax.lax.while_loop(cond, body, carry)
        return t, ret, length, episodes, unstable
    return jax.jit(run)


def parse_settings(text: str) -> dict:
    """'newton:2:4:off' -> Physics fields (solver, iterations, ls_iterations, euler damping)."""
    solver, iterations, ls_iterations, damping = text.split(":")
    return {"solver": solver, "iterations": int(iterations), "ls_iterations": int(ls_iterations),
            "euler_damping": {"on": True, "off": False}[damping]}


def settings_name(physics: dict) -> str:
    return (f"{physics['solver']}:{physics['iterations']}:{physics['ls_iterations']}:"
            f"{'on' if physics['euler_damping'] else 'off'}")


def candidates(task: str, n_steps: int, reference: bool, extra: list[str], extra_steps: int
               ) -> dict[str, tuple[dict, int, int]]:
    """Name -> (settings, max steps, min steps) for one task.

    'env_default' runs `n_steps`; with `reference`, 'model' (and 'model_euler_damping_off'
    where the model has damped joints) until every first episode has ended; each of `extra`
    `extra_steps`.
    """
    env = make_env(task)
    model = dataclasses.asdict(model_defaults(env.xml))
    runs = {"env_default": (dataclasses.asdict(env.physics), n_steps, n_steps)}
    damped = bool(env.mj_model.dof_damping.any())
    if reference:
        runs["model"] = (model, EPISODE, 0)
        if damped:
            runs["model_euler_damping_off"] = ({**model, "euler_damping": False}, EPISODE, 0)
    for text in extra:
        settings = parse_settings(text)
        if settings_name(settings) not in map(settings_name, (s for s, _, _ in runs.values())) \
                and (damped or not settings["euler_damping"]):
            runs[settings_name(settings)] = (settings, extra_steps, extra_steps)
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
    parser.add_argument("--no-reference", dest="reference", action="store_false",
                        help="skip the model's settings (a stability check only)")
    parser.add_argument("--extra", default="", help="more settings, e.g. newton:2:4:off,...")
    parser.add_argument("--extra-steps", type=int, default=1000)
    parser.add_argument("--out", default="benchmarks/results/physics_settings.json")
    args = parser.parse_args()
    key = jax.random.PRNGKey(0)
    extra = [x for x in args.extra.split(",") if x]

    def build(task, name, settings, n_steps, min_steps):
        env = make_env(task, **settings)
        compiled = make_evidence_run(env, args.envs).lower(key, 0, 0).compile()
        return name, env, compiled, n_steps, min_steps

    arguments = {k: v for k, v in vars(args).items() if k != "out"}
    results = {"device": jax.devices()[0].device_kind, "episode": EPISODE,
               "envs_per_action_kind": args.envs, "arguments": arguments, "tasks": {}}
    start = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(12) as pool:
        # Compile everything in the background; run each task as soon as its runs compiled.
        futures = {task: [pool.submit(build, task, name, *spec)
                          for name, spec in candidates(task, args.steps, args.reference, extra,
                                                       args.extra_steps).items()]
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
        t, ret, length, episodes, unstable = map(np.asarray,
                                                 compiled(key, n_steps, min_steps))
        seconds = time.perf_counter() - start
        returns[name] = ret
        res = out[name] = summarise(env, ret, length, unstable, int(t), seconds, n_envs)
        res["episodes"] = int(episodes.sum())
        print(f"{task:12s} {name:34s} steps {int(t):6d} unstable {res['unstable_steps']:5d}"
              f" | random {res['random_return_mean']:9.2f} ±{res['random_return_sem']:6.2f}"
              f" | sinusoid {res['sinusoid_return_mean']:9.2f} ±{res['sinusoid_return_sem']:6.2f}"
              f" | {res['ms_per_step']:6.2f} ms/step", flush=True)
    for name, ret in returns.items() if "model" in returns else ():
        ref, res = returns["model"], out[name]
        for kind, rows in (("random", slice(0, n_envs)), ("sinusoid", slice(n_envs, None))):
            diff, scale = ret[rows] - ref[rows], abs(ref[rows].mean())
            res[f"{kind}_vs_model"] = float(diff.mean() / scale)
            res[f"{kind}_vs_model_sem"] = float(diff.std() / np.sqrt(n_envs) / scale)
        random, sinusoid = (
            f"{100 * res[f'{k}_vs_model']:+6.1f}% ±{100 * res[f'{k}_vs_model_sem']:.1f}"
            for k in ("random", "sinusoid"))
        print(f"{task:12s} {name:34s} vs model: random {random} | sinusoid {sinusoid}", flush=True)
    return out


if __name__ == "__main__":
    main()

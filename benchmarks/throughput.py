"""Where a PGPS generation spends its time, against the floors, and the wall-clock of 1M steps.

For each task (paper configuration, Table 3-4), at the late-run episode cap T = T_max with
Q-filtering active:
  - population rollout, evaluation episodes, Q-filtering, CEM update and TD3 updates, each
    jitted on its own and timed (median of repeats, after compilation);
  - floors measured in the same process: (a) `n_frames` × bare `vmap(mjx.step)` per env step
    at the same batch; (b) one critic and one actor update written plainly in JAX (hand-written
    MLPs, optax Adam, a `lax.scan`), batch 256; (c) sequential env steps per 1M-step run ×
    (a) + updates per run × (b).
  - critic and actor updates per second of the project's TD3 at batch 256.
With --full-run TASK: the wall-clock of a whole 1M-step run (as the CLI runs it, without file
I/O: a test evaluation begun every 10,000 steps inside each generation) for 1 seed and for 5
seeds vmapped; compile time reported separately.

    python benchmarks/throughput.py --tasks halfcheetah hopper --full-run halfcheetah
"""

import argparse
import functools
import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

sys.path.insert(0, os.path.dirname(__file__))
from env_latency import bare_rollout  # noqa: E402  (sibling benchmark: the physics floor)

from pgps_jax import buffer as replay  # noqa: E402
from pgps_jax import cem  # noqa: E402
from pgps_jax.compile_ahead import compile_ahead  # noqa: E402
from pgps_jax.config import for_task  # noqa: E402
from pgps_jax.envs import TASKS, make_env  # noqa: E402
from pgps_jax.pgps import PGPS, episode_limit  # noqa: E402
from pgps_jax.rollout import run_episodes  # noqa: E402

SMOKE = "--smoke" in sys.argv
EVAL_EVERY = 10_000 if not SMOKE else 200
TOTAL_STEPS = 1_000_000 if not SMOKE else 1000
UPDATE_STEPS = 1000 if not SMOKE else 10    # updates per timed scan of the update benchmarks


def timed(fn, *args, repeats=5):
    """(seconds of the first call = compile + run, median seconds of later calls)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return first, float(np.median(times))


def sequential_steps_per_run(config) -> int:
    """Env steps one actor takes in a 1M-step run if no episode terminates (eq. 4 schedule)."""
    steps, sequential = config.warmup_steps, 0
    while steps < TOTAL_STEPS:
        limit = int(episode_limit(jnp.asarray(steps), config))
        steps += limit * config.pop_size
        sequential += limit
    return sequential + -(-config.warmup_steps // config.pop_size)


# ---------------------------------------------------------------- floors (b): plain updates
def _plain_mlp_init(key, sizes):
    keys = jax.random.split(key, len(sizes) - 1)
    return [(jax.random.uniform(k, (a, b), minval=-1, maxval=1) / np.sqrt(a), jnp.zeros(b))
            for k, a, b in zip(keys, sizes[:-1], sizes[1:])]


def _plain_mlp(params, x):
    for w, b in params[:-1]:
        x = jax.nn.elu(x @ w + b)
    w, b = params[-1]
    return x @ w + b


def plain_updates(obs_size, act_size, batch=256, capacity=1_000_000 if not SMOKE else 5000):
    """Floor (b): critic and actor updates as plainly as JAX allows, scanned UPDATE_STEPS."""
    key = jax.random.PRNGKey(0)
    data = jax.random.normal(key, (capacity, 2 * obs_size + act_size + 2))
    actor = _plain_mlp_init(key, [obs_size, 400, 300, act_size])
    critics = [_plain_mlp_init(jax.random.fold_in(key, i), [obs_size + act_size, 400, 300, 1])
               for i in range(2)]
    opt = optax.adam(1e-3)

    def unpack(rows):
        o, a = rows[:, :obs_size], rows[:, obs_size:obs_size + act_size]
        r, nxt = rows[:, obs_size + act_size], rows[:, obs_size + act_size + 1:-1]
        return o, a, r, nxt, rows[:, -1]

    def critic_step(carry, k):
        critics, opt_state, target_critics = carry
        o, a, r, nxt, d = unpack(data[jax.random.randint(k, (batch,), 0, capacity)])
        na = jnp.tanh(_plain_mlp(actor, nxt))
        y = r + 0.99 * d * jnp.minimum(*[_plain_mlp(c, jnp.concatenate([nxt, na], 1))[:, 0]
                                         for c in target_critics])

        def loss(cs):
            return sum(jnp.mean((_plain_mlp(c, jnp.concatenate([o, a], 1))[:, 0] - y) ** 2)
                       for c in cs)
        g = jax.grad(loss)(critics)
        upd, opt_state = opt.update(g, opt_state)
        critics = optax.apply_updates(critics, upd)
        target_critics = optax.incremental_update(critics, target_critics, 0.005)
        return (critics, opt_state, target_critics), None

    def actor_step(carry, k):
        actor, opt_state, target = carry
        o = unpack(data[jax.random.randint(k, (batch,), 0, capacity)])[0]

        def loss(p):
            act = jnp.tanh(_plain_mlp(p, o))
            return -jnp.mean(_plain_mlp(critics[0], jnp.concatenate([o, act], 1)))
        g = jax.grad(loss)(actor)
        upd, opt_state = opt.update(g, opt_state)
        actor = optax.apply_updates(actor, upd)
        return (actor, opt_state, optax.incremental_update(actor, target, 0.005)), None

    keys = jax.random.split(key, UPDATE_STEPS)
    run_critic = jax.jit(lambda c: jax.lax.scan(critic_step, c, keys)[0])
    run_actor = jax.jit(lambda c: jax.lax.scan(actor_step, c, keys)[0])
    _, critic_s = timed(run_critic, (critics, opt.init(critics), critics))
    _, actor_s = timed(run_actor, (actor, opt.init(actor), actor))
    return critic_s / UPDATE_STEPS, actor_s / UPDATE_STEPS


# ------------------------------------------------------------------ per-generation components
def bench_config(task: str):
    """The paper's configuration, or a tiny one with --smoke (a CPU check of this script)."""
    if not SMOKE:
        return for_task(task)
    return for_task(task, t_init=10, t_max=20, t_interval=1000, buffer_size=5000,
                    warmup_steps=200, q_filter_start=400, actor_hidden=(16, 16),
                    critic_hidden=(16, 16), eval_steps=20, sample_ratio=2)


def components(task: str) -> dict:
    config = bench_config(task)
    env = make_env(task)
    n, t_max = config.pop_size, config.t_max
    agent = PGPS(config, env)
    td3, unflatten, policy = agent.td3, agent.actor, agent.policy
    init = jax.jit(agent.init)
    init_s, _ = timed(init, jax.random.PRNGKey(0), repeats=0)
    state = init(jax.random.PRNGKey(0))
    state = state.replace(total_steps=jnp.asarray(config.q_filter_start, jnp.int32))
    key = jax.random.PRNGKey(1)
    population = cem.ask(key, state.cem, n)
    reset_keys = jax.random.split(key, n)

    rollout = jax.jit(lambda p: run_episodes(env, policy, p, reset_keys, jnp.full((n,), t_max),
                                             t_max))
    _, rollout_s = timed(rollout, population, repeats=3)
    lengths = np.asarray(rollout(population).lengths)
    evaluate = jax.jit(agent.evaluate)
    _, eval_s = timed(evaluate, agent.evaluated_actors(state), jax.random.PRNGKey(100),
                      repeats=3)
    qfilter = jax.jit(lambda s, k: agent._population(s, k, k, k))
    _, qfilter_s = timed(qfilter, state, key)
    returns = jax.random.normal(key, (n,))
    tell = jax.jit(functools.partial(cem.tell, top_k=config.top_k, sigma_limit=config.sigma_limit,
                                     sigma_decay=config.sigma_decay,
                                     divide_by_k=config.cem_divide_by_k))
    _, tell_s = timed(tell, state.cem, population, returns)
    num_update = n * t_max // config.update_blocks
    train = jax.jit(lambda s: td3.train(s.td3, s.buffer, key, jnp.asarray(num_update),
                                        num_update, unflatten(s.cem.elite),
                                        jnp.asarray(False), s.beta))
    _, train_s = timed(train, state, repeats=2)
    step = jax.jit(agent.generation_step)
    no_eval = state.replace(evaluation=state.evaluation.replace(
        next_due=jnp.asarray(2**30, jnp.int32)))
    _, generation_s = timed(step, no_eval, repeats=2)
    _, generation_eval_s = timed(step, state, repeats=2)    # an evaluation begins alongside

    def critic_update(t, batch, k):     # standalone: with its own π' forward pass
        noise = td3.smoothing_noise(k, (256, env.action_size))
        return td3.critic_update(t, batch, td3.target_actions(t.actor_target, batch.next_obs,
                                                              noise))[0]
    critic_fn = jax.jit(lambda s: jax.lax.scan(
        lambda t, k: (critic_update(t, replay.sample(s.buffer, k, 256), k), None),
        s.td3, jax.random.split(key, UPDATE_STEPS))[0])
    no_elite = jnp.zeros((256, env.action_size))
    actor_fn = jax.jit(lambda s: jax.lax.scan(
        lambda t, k: (td3.actor_update(t, replay.sample(s.buffer, k, 256).obs, no_elite,
                                       jnp.asarray(0.0))[0], None),
        s.td3, jax.random.split(key, UPDATE_STEPS))[0])
    _, critic_scan_s = timed(critic_fn, state)
    _, actor_scan_s = timed(actor_fn, state)

    # floors measured in this process
    data = jax.vmap(env.reset)(reset_keys).pipeline_state
    bare = jax.jit(bare_rollout(env, n, 100))
    _, bare_s = timed(bare, data, key)
    bare_ms = bare_s / 100 * 1e3
    plain_critic_s, plain_actor_s = plain_updates(env.observation_size, env.action_size)
    sequential = sequential_steps_per_run(config)
    updates = TOTAL_STEPS
    env_ms = rollout_s / max(int(lengths.max()), 1) * 1e3
    eval_ms = eval_s / config.eval_steps * 1e3
    return {
        "task": task, "pop_size": n, "T": t_max, "episode_lengths": lengths.tolist(),
        "init_compile_and_run_s": init_s,
        "generation_ms": {
            "population_rollout": rollout_s * 1e3, "evaluation_30_episodes": eval_s * 1e3,
            "q_filter": qfilter_s * 1e3, "cem_update": tell_s * 1e3,
            "td3_updates": train_s * 1e3, "generation_step_total": generation_s * 1e3,
            "generation_step_total_with_eval_alongside": generation_eval_s * 1e3,
            "generation_T": int(episode_limit(state.total_steps, config))},
        "per_env_step_ms": {"population": env_ms, "evaluation": eval_ms, "floor_bare_mjx": bare_ms,
                            "population_over_floor": env_ms / bare_ms},
        "per_update_us": {
            "critic": critic_scan_s / UPDATE_STEPS * 1e6, "actor": actor_scan_s / UPDATE_STEPS * 1e6,
            "floor_critic": plain_critic_s * 1e6, "floor_actor": plain_actor_s * 1e6,
            "td3_train_per_update_pair": train_s / (config.update_blocks * num_update) * 1e6},
        "updates_per_s": {"critic": UPDATE_STEPS / critic_scan_s, "actor": UPDATE_STEPS / actor_scan_s},
        "run_1m_floor_s": {
            "sequential_env_steps": sequential,
            "env": sequential * bare_ms / 1e3,
            "updates": updates * (plain_critic_s + plain_actor_s),
            "total": sequential * bare_ms / 1e3 + updates * (plain_critic_s + plain_actor_s)},
    }


# ---------------------------------------------------------------------------- full 1M-step run
def compile_run(config, env, keys, eval_keys, vmapped: bool, end_of_run: bool = True):
    """A run's programs compiled as the CLI compiles them: `init` and the two phases of a
    generation side by side, then (with `end_of_run`) `evaluate` in the background. With `vmapped`, each program is vmapped over the seeds of `keys`.
    Returns {name: future of its compiled program}, the `time.perf_counter()` at which the
    compilation began (once `init`'s output shapes were known) and the seconds until the two
    phases, and until `init` as well, were compiled."""
    agent = PGPS(config, env)
    batched = jax.vmap if vmapped else (lambda fn: fn)

    def jit(fn, donate=True):
        return jax.jit(batched(fn), donate_argnums=0 if donate else ())
    programs = {"init": jit(agent.init, donate=False), "play": jit(agent.play),
                "learn": jit(agent.learn), "evaluate": jit(agent.evaluate, donate=False)}
    abstract = jax.eval_shape(programs["init"], keys, eval_keys)
    start = time.perf_counter()
    args = {"init": (keys, eval_keys), "play": (abstract,),
            "learn": jax.eval_shape(programs["play"], abstract),
            "evaluate": (jax.eval_shape(batched(agent.evaluated_actors), abstract), eval_keys)}
    compiled = compile_ahead(
        {name: (programs[name], args[name]) for name in ("init", "play", "learn")},
        later={"evaluate": (programs["evaluate"], args["evaluate"])} if end_of_run else None)
    compiled["play"].result(), compiled["learn"].result()
    phases_s = time.perf_counter() - start
    compiled["init"].result()
    return compiled, start, phases_s, time.perf_counter() - start


def full_run(task: str, seeds: int) -> dict:
    """A whole 1M-step run as the CLI runs it, without file I/O: programs compiled ahead of
    time side by side (`init` and the two phases of a generation, then the two end-of-run
    programs), a test evaluation begun every 10k steps inside each generation, the one
    under way finished and the final state evaluated at the end. Wall-clock, compile time,
    generations (each timed in its two phases, with a wait between them, and whether it
    trained on the augmented loss) and the eval curve of μ."""
    config = bench_config(task).replace(eval_every=EVAL_EVERY)
    env = make_env(task)
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    eval_keys = jax.vmap(lambda s: jax.random.PRNGKey(s + 100))(jnp.arange(seeds))
    if seeds == 1:
        keys, eval_keys = keys[0], eval_keys[0]
    compiled, start, step_compile_s, compile_s = compile_run(config, env, keys, eval_keys,
                                                             vmapped=seeds > 1)
    init, play, learn = (compiled[name].result() for name in ("init", "play", "learn"))
    state = jax.block_until_ready(init(keys, eval_keys))
    init_run_s = time.perf_counter() - start - compile_s
    curve, generations = [], 0
    per_generation = {"total_s": [], "play_s": [], "learn_s": [], "episode_limit": [],
                      "interaction_steps": [], "guided": []}

    def record(metrics, *extra):
        """Adds an evaluation that ended to the curve; returns the `extra` metrics (host)."""
        done, step_at, mu, *values = jax.device_get(
            [metrics[k] for k in ("eval/done", "eval/step", "eval/mu_mean", *extra)])
        if np.any(done):
            curve.append((np.asarray(step_at).tolist(), np.asarray(mu).tolist()))
        return values

    while int(np.min(jax.device_get(state.total_steps))) < TOTAL_STEPS:
        t = time.perf_counter()
        played = jax.block_until_ready(play(state))    # one wait more: the phases timed apart
        t_played = time.perf_counter()
        state, metrics = learn(*played)
        generations += 1
        limit, steps, guided = record(metrics, "gen/episode_limit", "gen/interaction_steps",
                                      "td3/fell_behind")
        t_learned = time.perf_counter()
        for column, value in (("total_s", t_learned - t), ("play_s", t_played - t),
                              ("learn_s", t_learned - t_played),
                              ("episode_limit", np.asarray(limit).max().tolist()),
                              ("interaction_steps", np.asarray(steps).max().tolist()),
                              ("guided", np.asarray(guided).tolist())):
            per_generation[column].append(value)
    end = time.perf_counter()
    evaluate = compiled["evaluate"].result()
    tests = state.evaluation
    if np.any(jax.device_get(tests.active)):   # played to its end from its start, as the CLI
        evaluate(tests.actors, tests.key)
    agent = PGPS(config, env)
    actors = (jax.vmap(agent.evaluated_actors) if seeds > 1 else agent.evaluated_actors)(state)
    final = np.asarray(evaluate(actors, tests.key)["eval/mu_mean"]).tolist()
    wall = time.perf_counter() - start
    end_s = time.perf_counter() - end
    return {"task": task, "seeds": seeds, "wall_s_including_compile": wall,
            "compile_s": compile_s, "generation_phases_compile_s": step_compile_s,
            "init_run_s": init_run_s, "generations_s": sum(per_generation["total_s"]),
            "end_s": end_s, "generations": generations, "evaluations": len(curve) + 1,
            "final_eval_mu_mean": final, "eval_curve_every_10th": curve[::10],
            "per_generation": per_generation}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=list(TASKS))
    parser.add_argument("--full-run", nargs="*", default=[], metavar="TASK")
    parser.add_argument("--seeds", nargs="*", type=int, default=[1, 5])
    parser.add_argument("--out", default="benchmarks/results/throughput.json")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    result = {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "commit": commit,
              "xla_flags": os.environ.get("XLA_FLAGS", ""),
              "components": [], "full_runs": []}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)

    def record(kind, entry):
        result[kind].append(entry)
        print(json.dumps(entry), flush=True)
        with open(args.out, "w") as f:      # after every entry: a cut-off run keeps its part
            json.dump(result, f, indent=1)

    for task in args.tasks:
        record("components", components(task))
    for task in args.full_run:
        for seeds in args.seeds:
            record("full_runs", full_run(task, seeds))


if __name__ == "__main__":
    main()

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
With --updates-only: the TD3 updates and floor (b) alone, e.g. to compare XLA's options (one
process per variant, each under its XLA_FLAGS). With --full-run TASK: the wall-clock of a
whole 1M-step run (as the CLI runs it, without file I/O: a test evaluation begun every 10,000
steps inside each generation) for 1 seed and for 5 seeds vmapped; compile time reported
separately.

    python -m benchmarks.throughput --tasks halfcheetah hopper --full-run halfcheetah
    XLA_FLAGS=--xla_gpu_enable_triton_gemm=false python -m benchmarks.throughput \
        --tasks halfcheetah --updates-only --out runs/updates_cublas.json
"""

import argparse
import functools
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from benchmarks.env_latency import bare_rollout
from benchmarks.profile_generation import SMOKE_SIZES
from benchmarks.timing import physics_record, provenance, results_path, timed
from pgps_jax.agent import buffer as replay
from pgps_jax.agent import cem
from pgps_jax.agent.config import EvaluationConfig, for_task
from pgps_jax.agent.pgps import PGPS, episode_limit
from pgps_jax.agent.rollout import run_episodes
from pgps_jax.cli import loop
from pgps_jax.cli.assignments import env_assignments
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import TASKS, make_env

SMOKE = "--smoke" in sys.argv
TESTS = EvaluationConfig(every=10_000) if not SMOKE else EvaluationConfig(every=200, steps=20)
TOTAL_STEPS = 1_000_000 if not SMOKE else 1000
UPDATE_STEPS = 1000 if not SMOKE else 10    # updates per timed scan of the update benchmarks


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
    return for_task(task, **(SMOKE_SIZES if SMOKE else {}))


def late_run_state(task: str, env_kwargs: dict):
    """The agent of `task`'s benchmark configuration, a fresh state moved to the step at which
    Q-filtering starts, and the seconds its `init` took to compile and run."""
    config = bench_config(task)
    agent = PGPS(config, make_env(task, **env_kwargs), TESTS)
    init = jax.jit(agent.init)
    init_s, _ = timed(init, jax.random.PRNGKey(0), repeats=0)
    state = init(jax.random.PRNGKey(0))
    return agent, state.replace(total_steps=jnp.asarray(config.q_filter_start, jnp.int32)), init_s


def update_timings(agent, state, key) -> dict:
    """The TD3 updates at batch 256: a generation's schedule (`td3.train`, N·T_max pairs, the
    actor on L^O), the critic update alone (with its own π' forward pass) and the actor update
    alone, each over UPDATE_STEPS, with floor (b) measured in the same process."""
    config, td3, env = agent.config, agent.td3, agent.env
    num_update = config.pop_size * config.t_max // config.update_blocks
    train = jax.jit(lambda s: td3.train(s.td3, s.buffer, key, jnp.asarray(num_update),
                                        num_update, agent.actor(s.cem.elite),
                                        jnp.asarray(False), s.beta))
    _, train_s = timed(train, state, repeats=2)

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
    plain_critic_s, plain_actor_s = plain_updates(env.observation_size, env.action_size)
    return {
        "td3_updates_ms": train_s * 1e3,
        "per_update_us": {
            "critic": critic_scan_s / UPDATE_STEPS * 1e6,
            "actor": actor_scan_s / UPDATE_STEPS * 1e6,
            "floor_critic": plain_critic_s * 1e6, "floor_actor": plain_actor_s * 1e6,
            "td3_train_per_update_pair": train_s / (config.update_blocks * num_update) * 1e6},
        "updates_per_s": {"critic": UPDATE_STEPS / critic_scan_s,
                          "actor": UPDATE_STEPS / actor_scan_s},
        "floor_update_pair_s": plain_critic_s + plain_actor_s}


def components(task: str, env_kwargs: dict) -> dict:
    agent, state, init_s = late_run_state(task, env_kwargs)
    config, env, policy = agent.config, agent.env, agent.policy
    n, t_max = config.pop_size, config.t_max
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
    qfilter = jax.jit(lambda s, k: agent.population(s, k, k, k))
    _, qfilter_s = timed(qfilter, state, key)
    returns = jax.random.normal(key, (n,))
    tell = jax.jit(functools.partial(cem.tell, top_k=config.top_k, sigma_limit=config.sigma_limit,
                                     sigma_decay=config.sigma_decay,
                                     divide_by_k=config.cem_divide_by_k))
    _, tell_s = timed(tell, state.cem, population, returns)
    updates = update_timings(agent, state, key)
    step = jax.jit(agent.generation_step)
    no_eval = state.replace(evaluation=state.evaluation.replace(
        next_due=jnp.asarray(2**30, jnp.int32)))
    _, generation_s = timed(step, no_eval, repeats=2)
    _, generation_eval_s = timed(step, state, repeats=2)    # an evaluation begins alongside

    # floors measured in this process
    data = jax.vmap(env.reset)(reset_keys).pipeline_state
    bare = jax.jit(bare_rollout(env, n, 100))
    _, bare_s = timed(bare, data, key)
    bare_ms = bare_s / 100 * 1e3
    sequential = sequential_steps_per_run(config)
    env_ms = rollout_s / max(int(lengths.max()), 1) * 1e3
    eval_ms = eval_s / TESTS.steps * 1e3
    return {
        "task": task, "physics": physics_record(env), "pop_size": n, "T": t_max,
        "episode_lengths": lengths.tolist(),
        "init_compile_and_run_s": init_s,
        "generation_ms": {
            "population_rollout": rollout_s * 1e3, "evaluation_30_episodes": eval_s * 1e3,
            "q_filter": qfilter_s * 1e3, "cem_update": tell_s * 1e3,
            "td3_updates": updates["td3_updates_ms"], "generation_step_total": generation_s * 1e3,
            "generation_step_total_with_eval_alongside": generation_eval_s * 1e3,
            "generation_T": int(episode_limit(state.total_steps, config))},
        "per_env_step_ms": {"population": env_ms, "evaluation": eval_ms, "floor_bare_mjx": bare_ms,
                            "population_over_floor": env_ms / bare_ms},
        "per_update_us": updates["per_update_us"], "updates_per_s": updates["updates_per_s"],
        "run_1m_floor_s": {
            "sequential_env_steps": sequential,
            "env": sequential * bare_ms / 1e3,
            "updates": TOTAL_STEPS * updates["floor_update_pair_s"],
            "total": sequential * bare_ms / 1e3 + TOTAL_STEPS * updates["floor_update_pair_s"]},
    }


# ---------------------------------------------------------------------------- full 1M-step run
def full_run(task: str, seeds: int, env_kwargs: dict) -> dict:
    """A whole 1M-step run through the CLI's loop (`pgps_jax.cli.loop`), without file I/O:
    programs compiled ahead of time side by side, a test evaluation begun every 10,000 steps
    inside each generation, the one under way finished and the final state evaluated at the
    end. Wall-clock, compile time, generations (each timed in its two phases, with a wait
    between them, and whether it trained on the augmented loss) and the eval curve of μ."""
    env = make_env(task, **env_kwargs)
    agent = PGPS(bench_config(task), env, TESTS)
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    eval_keys = jax.vmap(lambda s: jax.random.PRNGKey(s + 100))(jnp.arange(seeds))
    if seeds == 1:
        keys, eval_keys = keys[0], eval_keys[0]
    start = time.perf_counter()
    programs = loop.Programs.compile(agent, keys, eval_keys, seeds=seeds > 1)
    programs.futures["play"].result(), programs.futures["learn"].result()
    phases_compile_s = time.perf_counter() - start
    init = programs["init"]
    compile_s = time.perf_counter() - start
    state = jax.block_until_ready(init(keys, eval_keys))
    init_run_s = time.perf_counter() - start - compile_s
    curve = []
    per_generation = {"total_s": [], "play_s": [], "learn_s": [], "episode_limit": [],
                      "interaction_steps": [], "guided": []}
    while int(np.min(jax.device_get(state.total_steps))) < TOTAL_STEPS:
        state, done = loop.generation(programs, state, time_phases=True)
        m = done.metrics
        if np.any(m["eval/done"]):
            curve.append((np.asarray(m["eval/step"]).tolist(),
                          np.asarray(m["eval/mu_mean"]).tolist()))
        for column, value in (("total_s", done.seconds), ("play_s", done.play_seconds),
                              ("learn_s", done.seconds - done.play_seconds),
                              ("episode_limit", np.max(m["gen/episode_limit"]).tolist()),
                              ("interaction_steps", np.max(m["gen/interaction_steps"]).tolist()),
                              ("guided", np.asarray(m["td3/guided_loss"]).tolist())):
            per_generation[column].append(value)
    end = time.perf_counter()
    state, finished = loop.finish(programs, state)
    wall = time.perf_counter() - start
    return {"task": task, "seeds": seeds, "physics": physics_record(env),
            "wall_s_including_compile": wall,
            "compile_s": compile_s, "generation_phases_compile_s": phases_compile_s,
            "init_run_s": init_run_s, "generations_s": sum(per_generation["total_s"]),
            "end_s": time.perf_counter() - end, "generations": len(per_generation["total_s"]),
            "evaluations": len(curve) + 1,
            "final_eval_mu_mean": np.asarray(finished.final["eval/mu_mean"]).tolist(),
            "eval_curve_every_10th": curve[::10], "per_generation": per_generation}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=list(TASKS))
    parser.add_argument("--full-run", nargs="*", default=[], metavar="TASK")
    parser.add_argument("--seeds", nargs="*", type=int, default=[1, 5])
    parser.add_argument("--out", help="default: benchmarks/results/throughput.json (with "
                        "--updates-only, update_timings.json); with "
                        "--smoke, the same name in a temporary directory")
    parser.add_argument("--env", nargs="*", default=[], metavar="NAME=VALUE",
                        help="physics settings for every task (`make_env`'s arguments), e.g. "
                        "fused_solve=false matmul_precision=default")
    parser.add_argument("--updates-only", action="store_true",
                        help="time only the TD3 updates and floor (b), e.g. under other "
                        "XLA_FLAGS")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    try:
        env_kwargs = env_assignments(args.env)
    except UsageError as e:
        parser.error(str(e))
    default = "update_timings.json" if args.updates_only else "throughput.json"
    args.out = results_path(args.out, f"benchmarks/results/{default}", args.smoke)
    result = {**provenance(),
              "xla_flags": os.environ.get("XLA_FLAGS", ""),
              "components": [], "updates": [], "full_runs": []}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)

    def record(kind, entry):
        result[kind].append(entry)
        print(json.dumps(entry), flush=True)
        with open(args.out, "w") as f:      # after every entry: a cut-off run keeps its part
            json.dump(result, f, indent=1)

    for task in args.tasks:
        if args.updates_only:
            agent, state, _ = late_run_state(task, env_kwargs)
            record("updates", {"task": task, "physics": physics_record(agent.env),
                               **update_timings(agent, state, jax.random.PRNGKey(1))})
        else:
            record("components", components(task, env_kwargs))
    for task in args.full_run:
        for seeds in args.seeds:
            record("full_runs", full_run(task, seeds, env_kwargs))


if __name__ == "__main__":
    main()

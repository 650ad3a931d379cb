"""Table 1's computational time split: TD3 update, actors evaluation, population generation
and CEM update, per cumulative model (Base; + P→E; + E→P; + Q-filter; + increasing steps).

As the paper measures it, in wall-clock time. On each task, one late-run generation (the
paper's configuration, at T = T_max with Q-filtering due, a full buffer of random rows, no
test evaluation under way) runs `--repeats` times per model of the `table1` grid, and so
does each of three of its parts as a jitted program of its own, on the inputs that the
generation gave it: population generation (`PGPS.generated_population`), CEM update
(`PGPS.cem_update`) and TD3 update (`PGPS.td3_update`: the buffer's insertion and the
updates). Actors evaluation is the rest of the generation: its rollout, with the
bookkeeping around the parts (key splits, metrics: microseconds against the rollout's
milliseconds to seconds), so the four columns add up to the generation, as the paper's do.
Medians of the repeats, after an untimed run; each of the generation's runs is kept too
(`generation_ms_runs`), to show their spread.

The models are states of one program that switch their couplings
(`pgps_jax.agent.couplings`), so a task compiles its generation once. Two things make the
generation stand for a late run's: every episode lasts T (`FullEpisodes`; the initialised
actors would fall at once on hopper, walker2d and ant), and the TD3 actor fell behind
(`lagging_generation`), so the models with EA→PG pay for L^A (an upper bound on its cost:
over a run, only the generations in which the actor lags do). Times are per generation and,
as in the paper, normalised by the Base model's generation. The parts' shares at T = T_max
stand for their sums over a run's schedule of T (so the `+ increasing steps` row cannot show
what its schedule saves). Actors evaluation includes stepping the idle slots of the test
evaluation beside the population.

    python -m benchmarks.time_split --tasks halfcheetah walker2d ant
    python -m benchmarks.time_split --tasks halfcheetah --smoke   # tiny sizes: a CPU check

Writes `benchmarks/results/time_split.json`, and Table 1's columns averaged over the tasks
(`table1_time`) beside it in `time_split.md`.
"""

import argparse
import functools
import json
import time
from typing import Any, Callable

from brax.envs.base import Wrapper
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.profile_generation import SMOKE_SIZES, late_state, tests_of
from benchmarks.timing import provenance, repeated_seconds, results_path, timed
from pgps_jax.agent.base import Played
from pgps_jax.agent.config import for_task
from pgps_jax.agent.couplings import couplings_of
from pgps_jax.agent.pgps import PGPS
from pgps_jax.cli.run_dir import write_atomic
from pgps_jax.envs import State, make_env
from pgps_jax.experiments.paper.grid import cells

TABLE1_TASKS = tuple(dict.fromkeys(cell.task for cell in cells("table1")))
"""The tasks of Table 1 (the paper's three)."""


class FullEpisodes(Wrapper):
    """The task with its termination off: every episode lasts its limit T, as a late run's
    actors mostly do. A freshly initialised actor falls within tens of steps on hopper,
    walker2d and ant, and both the rollout's loop (it stops once every episode has ended) and
    the TD3 updates (as many as the generation's env steps) would shrink with it. On a GPU,
    where the solver's iterations are unrolled, a physics step costs the same whatever the
    state."""

    def step(self, state: State, action: jax.Array) -> State:
        stepped = self.env.step(state, action)
        return stepped.replace(done=jnp.zeros_like(stepped.done))


def lagging_returns(returns: jax.Array, slot: int) -> jax.Array:
    """`returns` [N ≥ 3] with `slot`'s set to min − N·(1 + range) of the others: below
    mean − std of them all (Algorithm 1's test of a TD3 actor that fell behind), since the
    mean is at least ((N − 1)·min + that) / N and the std at most half the range."""
    others = jnp.delete(returns, slot)
    low, spread = jnp.min(others), jnp.max(others) - jnp.min(others)
    return returns.at[slot].set(low - returns.shape[0] * (1.0 + spread))


def lagging_generation(agent: PGPS, state) -> tuple[Any, dict, Played]:
    """One generation (`play`, then `learn`) in which the TD3 actor, where it joined the
    population (PG→EA; slot N − 1, no probe slot), fell behind (`lagging_returns`): a model
    with EA→PG trains on L^A (eq. 2-3), which over a run only the generations it lags in do,
    so its cost here is an upper bound. Returns the next state, the metrics and the
    generation's `Played` (the inputs of its parts, `parts_of`)."""
    played_state, played = agent.play(state)
    returns = played.episodes.returns
    lagging = lagging_returns(returns, agent.config.pop_size - 1)
    returns = jnp.where(agent.switch(state, "pg_guides_ea"), lagging, returns)
    played = played.replace(episodes=played.episodes.replace(returns=returns))
    return *agent.learn(played_state, played), played


def parts_of(agent: PGPS) -> dict[str, tuple[Callable, Callable]]:
    """The generation's parts other than the actors evaluation: per part, a function that
    calls the agent's own method for it, and a function that builds its arguments from what
    the generation gave the part (the state it started from, its `Played`, the state after it
    and whether TD3 trained on L^A), with which it computes what the generation computed in
    it. The CEM update takes its three arrays alone; the others take the state (and
    `Played`) whole, whose unread leaves jit leaves out of the program."""
    n = agent.config.pop_size

    def population_generation(state, td3_turn):
        keys = jax.random.split(state.key, 6)[:3]  # `play`'s sample, candidate, states keys
        return agent.generated_population(state, *keys, td3_turn)

    def td3_update(state, played, elite, guided):
        return agent.td3_update(state, played, agent.actor(elite), guided)

    return {
        "population_generation": (
            population_generation, lambda state, played, after, guided: (
                state, played.td3_turn)),
        "cem_update": (
            agent.cem_update, lambda state, played, after, guided: (
                state.cem, played.population, played.episodes.returns[:n])),
        "td3_update": (
            td3_update, lambda state, played, after, guided: (
                state, played, after.cem.elite, guided))}


def task_program(task: str, smoke: bool) -> tuple[PGPS, dict[str, Any]]:
    """The agent of the task's late-run generation (the paper's configuration, `FullEpisodes`)
    and, per model of the `table1` grid (Base first), the late-run state that switches the
    model's couplings (`couplings_of`), at a generation where the TD3 actor takes its turn
    (every F generations: Algorithm 1 line 11)."""
    sizes = SMOKE_SIZES if smoke else {}
    config = for_task(task, **sizes)
    env = FullEpisodes(make_env(task))
    agent = PGPS(config, env, tests_of(smoke))
    state = late_state(config, env, smoke)
    state = state.replace(
        evaluation=state.evaluation.replace(next_due=jnp.asarray(2**30, jnp.int32)),  # none
        generation=jnp.asarray(config.td3_to_cem_period - 1, jnp.int32))  # the TD3 actor's turn
    states = {cell.config: state.replace(couplings=couplings_of(
        config, for_task(task, **dict(cell.overrides), **sizes)))
        for cell in cells("table1", (task,))}
    return agent, states


def model_split(generation: Callable, parts: dict[str, tuple[Callable, Callable]], state,
                repeats: int) -> dict:
    """One model's generation (`generation`: the jitted `lagging_generation`) and its parts
    (`parts_of`, their functions jitted) in milliseconds, medians of `repeats` runs after an
    untimed one, the actors evaluation being the generation's rest (a warning where nothing
    is left for it); and whether its TD3 actor trained on L^A."""
    after, metrics, played = generation(state)
    guided = metrics["td3/guided_loss"]
    runs = [1e3 * s for s in repeated_seconds(generation, state, repeats=repeats)]
    total = float(np.median(runs))
    ms = {name: 1e3 * timed(part, *inputs(state, played, after, guided), repeats=repeats)[1]
          for name, (part, inputs) in parts.items()}
    ms["actors_evaluation"] = total - sum(ms.values())
    if ms["actors_evaluation"] <= 0:  # kept as measured: the table shows it
        print(f"warning: the parts timed alone ({ms}) took as long as the generation "
              f"({total:.3f} ms), leaving no time for its actors evaluation", flush=True)
    return {"ms_per_generation": ms, "total_ms": total, "generation_ms_runs": runs,
            "guided": bool(guided)}


def task_split(task: str, repeats: int, smoke: bool) -> list[dict]:
    """The time split of each of the task's models (Base first), one after the other, each
    program compiled once for them all (RuntimeError unless exactly the models with EA→PG
    trained on L^A)."""
    started = time.perf_counter()
    agent, states = task_program(task, smoke)
    print(f"{task}: late-run state built ({time.perf_counter() - started:.0f} s)", flush=True)
    generation = jax.jit(functools.partial(lagging_generation, agent))
    parts = {name: (jax.jit(part), inputs) for name, (part, inputs) in parts_of(agent).items()}
    splits = []
    for model, state in states.items():
        split = {"model": model, **model_split(generation, parts, state, repeats)}
        guided = split.pop("guided")
        if guided != bool(state.couplings.ea_guides_pg):
            raise RuntimeError(f"{task} {model}: the TD3 actor trained on L^A {guided}, "
                               f"against the model's EA→PG")
        splits.append(split)
        print(f"{task}: {model} timed ({time.perf_counter() - started:.0f} s)", flush=True)
    return splits


TABLE1_COLUMNS = (("td3_update", "TD3 update"), ("actors_evaluation", "actors evaluation"),
                  ("population_generation", "population generation"),
                  ("cem_update", "CEM update"))
"""Table 1's columns of normalised computational time, in the paper's order."""


def table1_time(tasks: list[dict]) -> str:
    """Table 1's normalised computational time as a Markdown table: per model, each phase's
    time over the Base model's total on its task, averaged over the tasks (as the paper
    averages its three games), and their sum."""
    names = [model["model"] for model in tasks[0]["models"]]
    lines = ["| model | sum | " + " | ".join(title for _, title in TABLE1_COLUMNS) + " |",
             "|" + "---|" * (2 + len(TABLE1_COLUMNS))]
    for name in names:
        shares = [np.mean([next(m for m in task["models"] if m["model"] == name)
                           ["normalised"][phase] for task in tasks])
                  for phase, _ in TABLE1_COLUMNS]
        lines.append(f"| {name} | {sum(shares):.3f} | "
                     + " | ".join(f"{share:.3f}" for share in shares) + " |")
    tasks_line = "Averaged over " + ", ".join(task["task"] for task in tasks) + "."
    return "\n".join(lines + ["", tasks_line, ""])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=["halfcheetah", "walker2d", "ant"],
                        choices=TABLE1_TASKS)
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each program")
    parser.add_argument("--out", help="default: benchmarks/results/time_split.json; with "
                        "--smoke, the same name in a temporary directory")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats must be a positive integer, not {args.repeats}")
    out = results_path(args.out, "benchmarks/results/time_split.json", args.smoke)
    result = {**provenance(), "repeats": args.repeats, "tasks": []}
    for task in args.tasks:
        models = task_split(task, args.repeats, args.smoke)
        base = models[0]["total_ms"]
        for model in models:  # the paper's normalisation: the Base model's generation is 1
            model["normalised"] = {p: t / base for p, t in model["ms_per_generation"].items()}
            model["normalised_sum"] = model["total_ms"] / base
            print(json.dumps({"task": task, **model}), flush=True)
        result["tasks"].append({"task": task, "models": models})
        # after every task: a cut-off run keeps its part
        out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(out, json.dumps(result, indent=1).encode())
        write_atomic(out.with_suffix(".md"), table1_time(result["tasks"]).encode())
    print(f"written: {out}")


if __name__ == "__main__":
    main()

"""Table 1's computational time split: TD3 update, actors evaluation, population generation
and CEM update, per cumulative model (Base; + P→E; + E→P; + Q-filter; + increasing steps).

On each task, one late-run generation (the paper's configuration, at T = T_max with Q-filtering
due, a full buffer of random rows, no test evaluation under way) runs `--generations` times per
model of the `table1` grid under `jax.profiler.trace`. The models are states of one program
that switch their couplings (`pgps_jax.agent.couplings`), so a task compiles once. Two things
make the generation stand for a late run's: every episode lasts T (`FullEpisodes`; the
initialised actors would fall at once on hopper, walker2d and ant), and the TD3 actor fell
behind (`lagging_generation`), so the models with EA→PG pay for L^A (an upper bound on its
cost: over a run, only the generations in which the actor lags do). Each model is traced alone,
one after the other, after one untimed trace: a process's first trace runs slower (1.9× in
`--smoke` on the CPU) and would inflate the Base model's total, the denominator. Every device
operation of the trace is attributed to the phase whose JAX named scope
(`pgps_jax.agent.pgps.PHASES`) its HLO instruction carries; the rest (key splitting, metrics)
is `other`. Times are per generation and, as in the paper, normalised by the Base model's
total. The phases' shares at T = T_max stand for their sums over a run's schedule of T (so the
`+ increasing steps` row cannot show what its schedule saves). `actors_evaluation` includes
stepping the idle slots of the test evaluation beside the population; a kernel that XLA fused
from two phases counts for the phase of its output. The operations that no phase names are
listed under `unattributed`.

    python -m benchmarks.time_split --tasks halfcheetah walker2d ant
    python -m benchmarks.time_split --tasks halfcheetah --smoke   # tiny sizes: a CPU check

Writes `benchmarks/results/time_split.json`, and Table 1's columns averaged over the tasks
(`table1_time`) beside it in `time_split.md`.
"""

import argparse
import collections
import functools
import glob
import gzip
import json
import os
import re
import tempfile
import time
from typing import Any, Callable, Optional, Sequence

from brax.envs.base import Wrapper
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.profile_generation import late_state, tests_of
from benchmarks.timing import provenance
from pgps_jax.agent.config import for_task
from pgps_jax.agent.couplings import couplings_of
from pgps_jax.agent.pgps import PGPS, PHASES
from pgps_jax.envs import State, make_env
from pgps_jax.envs.physics import default_platform
from pgps_jax.experiments.paper.grid import cells

SMOKE = dict(t_init=10, t_max=20, t_interval=1000, buffer_size=5000, warmup_steps=200,
             q_filter_start=400, actor_hidden=(16, 16), critic_hidden=(16, 16), sample_ratio=2)
_COMPUTATION = re.compile(r"^\s*(?:ENTRY )?%?([\w.\-]+) .*\{\s*$")
_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%?([\w.\-]+) = ")
_OP_NAME = re.compile(r'metadata=\{[^}]*op_name="([^"]*)"')
_CALLED = re.compile(r"(?:calls|body|condition|to_apply|branch_computations|true_computation|"
                     r"false_computation)=\{?((?:%?[\w.\-]+(?:, )?)+)\}?")
_CONTAINER = re.compile(r" = .*?\s(?:while|conditional|call)\(")
"""Instructions whose time is that of the operations they run (not counted twice)."""
_EVENTS = 1 << 26
"""Device events a GPU profile keeps (XLA's default, 2M, holds two halfcheetah generations
with almost none to spare)."""


def _key(name: str) -> str:
    """An HLO instruction's name as a kernel's or a thunk's name spells it."""
    return re.sub(r"[.\-]", "_", name)


def _innermost(op_name: str, patterns: dict[str, re.Pattern]) -> Optional[str]:
    """The scope of `patterns` that starts last in the op_name path (the innermost), if any."""
    found = [(m.start(), scope) for scope, pattern in patterns.items()
             for m in pattern.finditer(op_name)]
    return max(found)[1] if found else None


def phases_of(hlo_text: str, scopes: Sequence[str] = PHASES) -> dict[str, Optional[str]]:
    """The phase of every HLO instruction of a compiled program (by its name's `_key`); None
    for a loop, conditional or call, whose time is that of the instructions it runs.

    An instruction's phase is the innermost of `scopes` in its op_name path (also as
    vmap(<scope>) in a vmapped program); one without (a fusion or copy that a compiler pass
    made) takes the phase of the instructions it calls, else that of the instruction calling
    the computation it lies in (a loop's body: the loop's)."""
    patterns = {p: re.compile(rf"(^|[/(]){p}([)/]|$)") for p in scopes}
    named, called, enclosing, callers, inner, containers = {}, {}, {}, {}, {}, set()
    computation = None
    for line in hlo_text.splitlines():
        start = _COMPUTATION.match(line)
        if start and " = " not in line:
            computation = start.group(1)
            continue
        match = _INSTRUCTION.match(line)
        if not match or computation is None:
            continue
        name = match.group(1)
        op_name = _OP_NAME.search(line)
        named[name] = _innermost(op_name.group(1), patterns) if op_name else None
        enclosing[name] = computation
        if _CONTAINER.search(line):
            containers.add(name)
        called[name] = [c.strip().lstrip("%") for group in _CALLED.findall(line)
                        for c in group.split(",") if c.strip()]
        for c in called[name]:
            callers.setdefault(c, name)
        if named[name]:
            inner.setdefault(computation, collections.Counter())[named[name]] += 1

    def phase(name: str, seen: frozenset = frozenset()) -> str:
        if named[name]:
            return named[name]
        within = collections.Counter()
        for c in called[name]:
            within.update(inner.get(c, {}))
        if within:
            return within.most_common(1)[0][0]
        caller = callers.get(enclosing[name])
        if caller is None or caller in seen:
            return "other"
        return phase(caller, seen | {name})

    return {_key(name): None if name in containers else phase(name) for name in named}


def counted_events(trace_file: str, phases: dict[str, Optional[str]], platform: str
                   ) -> list[tuple[dict, str, str]]:
    """(event, instruction, phase) of every device operation in a Perfetto JSON trace of a
    program run on `platform` ("gpu" or "cpu"): the GPU's kernels, or the CPU's operations
    other than its loops, conditionals and calls. Copies and memsets are left out."""
    with gzip.open(trace_file) as f:
        events = json.load(f)["traceEvents"]
    names = {e["pid"]: e["args"]["name"] for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    gpu = {pid for pid, name in names.items() if "gpu" in name.lower()}
    found = []
    for e in events:
        args = e.get("args", {})
        if e.get("ph") != "X" or (e.get("pid") not in gpu if platform == "gpu"
                                  else e.get("pid") in gpu or "hlo_op" not in args):
            continue
        # a kernel run inside a CUDA graph carries the graph's hlo_op: its own name is the
        # fusion's
        name = next((n for n in (_key(args.get("hlo_op", "")), _key(e["name"])) if n in phases),
                    _key(e["name"]))
        if name.lower().startswith(("memcpy", "memset")) or (name in phases
                                                            and phases[name] is None):
            continue
        found.append((e, name, phases.get(name, "other")))
    return found


def split(trace_file: str, phases: dict[str, Optional[str]], generations: int,
          platform: str) -> tuple[dict[str, float], dict[str, float]]:
    """Device milliseconds per generation of each of `PHASES` (`counted_events`), and of
    the operations counted as `other`, the longest first."""
    totals, unattributed = collections.Counter(), collections.Counter()
    for event, name, phase in counted_events(trace_file, phases, platform):
        totals[phase] += event["dur"]
        if phase == "other":
            unattributed[name] += event["dur"]
    per_generation = 1e3 * generations
    return ({p: totals[p] / per_generation for p in (*PHASES, "other")},
            {n: t / per_generation for n, t in unattributed.most_common(10)})


def trace_of(run: Callable[[], Any], log_dir: str) -> str:
    """Runs `run` (to the end of its outputs' computation) under JAX's profiler, keeping up to
    `_EVENTS` device events; returns the path of its Perfetto trace in `log_dir`."""
    options = jax.profiler.ProfileOptions()
    options.advanced_configuration = {"gpu_max_activity_api_events": _EVENTS,
                                      "gpu_max_callback_api_events": _EVENTS}
    with jax.profiler.trace(log_dir, create_perfetto_trace=True, profiler_options=options):
        jax.block_until_ready(run())
    return glob.glob(os.path.join(log_dir, "**", "perfetto_trace.json.gz"), recursive=True)[0]


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


def lagging_generation(agent: PGPS, state) -> tuple[Any, dict]:
    """One generation (`play`, then `learn`) in which the TD3 actor, where it joined the
    population (PG→EA; slot N − 1, no probe slot), fell behind (`lagging_returns`): a model
    with EA→PG trains on L^A (eq. 2-3), which over a run only the generations it lags in do,
    so its cost here is an upper bound."""
    state, played = agent.play(state)
    returns = played.episodes.returns
    lagging = lagging_returns(returns, agent.config.pop_size - 1)
    returns = jnp.where(agent.switch(state, "pg_guides_ea"), lagging, returns)
    played = played.replace(episodes=played.episodes.replace(returns=returns))
    return agent.learn(state, played)


def task_program(task: str, smoke: bool) -> tuple[Callable, dict[str, Any]]:
    """The task's jitted `lagging_generation` (the paper's configuration, `FullEpisodes`) and,
    per model of the `table1` grid (Base first), the late-run state that switches the
    model's couplings (`couplings_of`): one program times every model."""
    sizes = SMOKE if smoke else {}
    config = for_task(task, **sizes)
    env = FullEpisodes(make_env(task))
    agent = PGPS(config, env, tests_of(smoke))
    state = late_state(config, env, smoke)
    state = state.replace(evaluation=state.evaluation.replace(  # none under way
        next_due=jnp.asarray(2**30, jnp.int32)))
    states = {cell.config: state.replace(couplings=couplings_of(
        config, for_task(task, **dict(cell.overrides), **sizes)))
        for cell in cells("table1", (task,))}
    return jax.jit(functools.partial(lagging_generation, agent)), states


def model_split(model: str, compiled: jax.stages.Compiled, phases: dict[str, Optional[str]],
                state, generations: int) -> dict:
    """The time split of one model's late-run generation (`phases`: of the program's
    instructions, `phases_of`), traced alone; the program must have run once already."""
    with tempfile.TemporaryDirectory() as log_dir:
        trace = trace_of(lambda: [compiled(state) for _ in range(generations)], log_dir)
        ms, unattributed = split(trace, phases, generations, default_platform())
    return {"model": model, "ms_per_generation": ms, "total_ms": sum(ms.values()),
            "unattributed_ms": unattributed}


def task_split(task: str, generations: int, smoke: bool) -> list[dict]:
    """The time split of each of the task's models (Base first): the task's one program
    compiles, runs once per model (RuntimeError unless exactly the models with EA→PG trained
    on L^A), then each model is traced alone, one after the other."""
    started = time.perf_counter()

    def progress(what: str) -> None:
        print(f"{task}: {what} ({time.perf_counter() - started:.0f} s)", flush=True)

    step, states = task_program(task, smoke)
    progress("late-run state built")
    compiled = step.lower(next(iter(states.values()))).compile()
    phases = phases_of(compiled.as_text())
    progress("compiled")
    for model, state in states.items():  # every model's first run before any is traced
        _, metrics = jax.block_until_ready(compiled(state))
        if bool(metrics["td3/guided_loss"]) != bool(state.couplings.ea_guides_pg):
            raise RuntimeError(f"{task} {model}: the TD3 actor trained on L^A "
                               f"{bool(metrics['td3/guided_loss'])}, against the model's EA→PG")
    base = next(iter(states))
    with tempfile.TemporaryDirectory() as log_dir:  # a process's first trace runs slower
        trace_of(lambda: compiled(states[base]), log_dir)
    progress("run once per model, and traced once untimed")
    splits = []
    for model, state in states.items():
        splits.append(model_split(model, compiled, phases, state, generations))
        progress(f"{model} traced")
    return splits


TABLE1_COLUMNS = (("td3_update", "TD3 update"), ("actors_evaluation", "actors evaluation"),
                  ("population_generation", "population generation"),
                  ("cem_update", "CEM update"), ("other", "other"))
"""Table 1's columns of normalised computational time, in the paper's order, and `other`."""


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
    parser.add_argument("--tasks", nargs="*", default=["halfcheetah", "walker2d", "ant"])
    parser.add_argument("--generations", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/results/time_split.json")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    result = {**provenance(), "tasks": []}
    for task in args.tasks:
        models = task_split(task, args.generations, args.smoke)
        base = models[0]["total_ms"]
        for model in models:  # the paper's normalisation: the Base model's total is 1
            model["normalised"] = {p: t / base for p, t in model["ms_per_generation"].items()}
            model["normalised_sum"] = model["total_ms"] / base
            print(json.dumps({"task": task, **model}), flush=True)
        result["tasks"].append({"task": task, "models": models})
        os.makedirs(os.path.dirname(args.out), exist_ok=True)
        with open(args.out, "w") as f:  # after every task: a cut-off run keeps its part
            json.dump(result, f, indent=1)
        with open(os.path.splitext(args.out)[0] + ".md", "w") as f:
            f.write(table1_time(result["tasks"]))


if __name__ == "__main__":
    main()

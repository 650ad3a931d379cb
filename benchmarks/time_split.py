"""Table 1's computational time split: TD3 update, actors evaluation, population generation
and CEM update, per cumulative model (Base; + P→E; + E→P; + Q-filter; + increasing steps).

For each model of the `table1` grid on a task (the paper's configuration with the model's
switches), one late-run generation (T = T_max, Q-filtering due, a full buffer of random rows,
no test evaluation under way) runs `--generations` times under `jax.profiler.trace`. Every
device operation of the trace is attributed to the phase whose JAX named scope
(`pgps_jax.agent.pgps.PHASES`) its HLO instruction carries; the rest (key splitting,
metrics) is `other`. Times are per generation and, as in the paper, normalised by the Base
model's total. A late-run generation stands for the whole run here: the phases' shares at
T = T_max, not their sums over a run's schedule of T.

    python -m benchmarks.time_split --tasks halfcheetah walker2d ant
    python -m benchmarks.time_split --tasks halfcheetah --smoke   # tiny sizes: a CPU check

Writes `benchmarks/results/time_split.json`.
"""

import argparse
import collections
import glob
import gzip
import json
import os
import re
import subprocess
import tempfile

import jax
import jax.numpy as jnp

from benchmarks.profile_generation import late_state
from pgps_jax.agent.config import EvaluationConfig, for_task
from pgps_jax.agent.pgps import PGPS, PHASES
from pgps_jax.envs import make_env
from pgps_jax.experiments.paper.grid import cells

SMOKE = dict(t_init=10, t_max=20, t_interval=1000, buffer_size=5000, warmup_steps=200,
             q_filter_start=400, actor_hidden=(16, 16), critic_hidden=(16, 16), sample_ratio=2)
_INSTRUCTION = re.compile(r'^\s*(?:ROOT )?%?([\w.\-]+) = .*metadata=\{[^}]*op_name="([^"]*)"')
_CONTAINERS = ("while", "conditional", "call")
"""Instructions whose time is that of the operations they run (not counted twice)."""


def _key(name: str) -> str:
    """An HLO instruction's name as a kernel's or a thunk's name spells it."""
    return re.sub(r"[.\-]", "_", name)


def phases_of(hlo_text: str) -> dict[str, str]:
    """The phase of every HLO instruction of a compiled program (by its name's `_key`)."""
    phases = {}
    for line in hlo_text.splitlines():
        match = _INSTRUCTION.match(line)
        if match and not match.group(1).startswith(_CONTAINERS):
            path = match.group(2).split("/")
            phases[_key(match.group(1))] = next((p for p in PHASES if p in path), "other")
    return phases


def split(trace_file: str, phases: dict[str, str], generations: int) -> dict[str, float]:
    """Device milliseconds per generation of each phase in a Perfetto JSON trace: the GPU's
    kernels, or on a CPU the program's leaf operations."""
    with gzip.open(trace_file) as f:
        events = json.load(f)["traceEvents"]
    names = {e["pid"]: e["args"]["name"] for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    gpu = {pid for pid, name in names.items() if "GPU" in name or "gpu" in name}
    totals = collections.Counter()
    for e in events:
        args = e.get("args", {})
        if e.get("ph") != "X" or not ("hlo_op" in args or e.get("pid") in gpu):
            continue
        name = _key(args.get("hlo_op") or e["name"])
        if name in phases:
            totals[phases[name]] += e["dur"]
        elif e.get("pid") in gpu and not name.lower().startswith(("memcpy", "memset")):
            totals["other"] += e["dur"]
    return {p: totals[p] / 1e3 / generations for p in (*PHASES, "other")}


def model_split(task: str, cell, generations: int, smoke: bool) -> dict:
    """The time split of one model's late-run generation on `task`."""
    config = for_task(task, **dict(cell.overrides), **(SMOKE if smoke else {}))
    env = make_env(task)
    agent = PGPS(config, env, EvaluationConfig(steps=20) if smoke else EvaluationConfig())
    state = late_state(config, env)
    state = state.replace(evaluation=state.evaluation.replace(  # none under way
        next_due=jnp.asarray(2**30, jnp.int32)))
    step = jax.jit(agent.generation_step)
    compiled = step.lower(state).compile()
    jax.block_until_ready(compiled(state))
    with tempfile.TemporaryDirectory() as log_dir:
        with jax.profiler.trace(log_dir, create_perfetto_trace=True):
            for _ in range(generations):
                out = compiled(state)
            jax.block_until_ready(out)
        trace = glob.glob(os.path.join(log_dir, "**", "perfetto_trace.json.gz"),
                          recursive=True)
        ms = split(trace[0], phases_of(compiled.as_text()), generations)
    return {"model": cell.config, "ms_per_generation": ms, "total_ms": sum(ms.values())}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=["halfcheetah", "walker2d", "ant"])
    parser.add_argument("--generations", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/results/time_split.json")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check the script")
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    result = {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "commit": commit,
              "tasks": []}
    for task in args.tasks:
        models = [model_split(task, cell, args.generations, args.smoke)
                  for cell in cells("table1", (task,))]
        base = models[0]["total_ms"]
        for model in models:  # the paper's normalisation: the Base model's total is 1
            model["normalised"] = {p: t / base for p, t in model["ms_per_generation"].items()}
            model["normalised_sum"] = model["total_ms"] / base
            print(json.dumps({"task": task, **model}), flush=True)
        result["tasks"].append({"task": task, "models": models})
        os.makedirs(os.path.dirname(args.out), exist_ok=True)
        with open(args.out, "w") as f:  # after every task: a cut-off run keeps its part
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()

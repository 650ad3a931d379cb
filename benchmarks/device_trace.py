"""Device time per named scope: a program run under JAX's profiler, and each device
operation of its trace attributed to the JAX named scope that its HLO instruction carries.

`phases_of` maps a compiled program's instructions to scopes (the stages of MJX's physics in
`benchmarks.physics_profile`, or the phases of a PGPS generation, `pgps_jax.agent.pgps.PHASES`),
`trace_of` profiles a run, and `counted_events` reads the trace's device operations with their
scopes.
"""

import collections
import glob
import gzip
import json
import os
import re
from typing import Any, Callable, Optional, Sequence

import jax

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


def phases_of(hlo_text: str, scopes: Sequence[str]) -> dict[str, Optional[str]]:
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


def trace_of(run: Callable[[], Any], log_dir: str) -> str:
    """Runs `run` (to the end of its outputs' computation) under JAX's profiler, keeping up to
    `_EVENTS` device events; returns the path of its Perfetto trace in `log_dir`."""
    options = jax.profiler.ProfileOptions()
    options.advanced_configuration = {"gpu_max_activity_api_events": _EVENTS,
                                      "gpu_max_callback_api_events": _EVENTS}
    with jax.profiler.trace(log_dir, create_perfetto_trace=True, profiler_options=options):
        jax.block_until_ready(run())
    return glob.glob(os.path.join(log_dir, "**", "perfetto_trace.json.gz"), recursive=True)[0]

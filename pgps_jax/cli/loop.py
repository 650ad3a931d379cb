"""The training loop of the CLI and the benchmarks: a run's programs, its generations and the
evaluations that end it, for one seed or a batch of seeds (vmapped).

`Programs.compile` jits an agent's `init`, `play`, `learn` (state donated) and `evaluate` and
compiles them ahead of time side by side (`compile_ahead`); `generation` runs `play` then
`learn` and fetches the metrics in one `jax.device_get`; `finish` plays the evaluation under
way to its end from its start and evaluates the state the run ends with, both with the
`evaluate` program. A caller loops `generation` until its budget and writes what it needs.
"""

import dataclasses
import functools
import time
import weakref
from concurrent.futures import Future
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax.agent.base import Agent, TrainState
from pgps_jax.cli.compile_ahead import compile_ahead


def state_shapes(agent: Agent, key: jax.Array, eval_key: jax.Array, seeds: bool = False):
    """The shapes and dtypes of `agent.init(key, eval_key)`'s TrainState (a checkpoint is
    restored into them), found without tracing the warm-up's physics."""
    unfilled = dataclasses.replace(agent, config=agent.config.replace(warmup_steps=0))
    return jax.eval_shape(jax.vmap(unfilled.init) if seeds else unfilled.init, key, eval_key)


@dataclasses.dataclass(frozen=True)
class Programs:
    """A run's compiled programs (futures until compiled) and its agent."""

    agent: Agent
    seeds: bool
    """Each program takes a batch of states, keys and actors (vmapped over seeds)."""
    futures: dict[str, Future]

    @classmethod
    def compile(cls, agent: Agent, key: jax.Array, eval_key: jax.Array, seeds: bool = False,
                sharding: Optional[jax.sharding.Sharding] = None, restored=None
                ) -> "Programs":
        """Starts compiling: `init` (unless `restored`) with `play` and `learn` side by side,
        then `evaluate` in the background. `key`, `eval_key`: as `init` takes them (with a
        leading seed axis if `seeds`). `sharding`: where every array of the state and of a
        generation lies (a batch of seeds split over devices); by default on one device.
        `restored`: the shapes of a state restored from a checkpoint (`state_shapes`), for a
        resumed run, which needs no `init`."""
        jitted = _jitted(agent, seeds, sharding)
        # A fresh run's init is traced once: `lower` reuses the trace.
        abstract = placed(jax.eval_shape(jitted["init"], key, eval_key) if restored is None
                          else restored, sharding)
        played = placed(jax.eval_shape(jitted["play"], abstract), sharding)
        programs = {"play": (jitted["play"], (abstract,)), "learn": (jitted["learn"], played)}
        if restored is None:
            programs["init"] = (jitted["init"], (key, eval_key))
        actors = placed(jax.eval_shape(jitted["evaluated_actors"], abstract), sharding)
        futures = compile_ahead(programs, later={
            "evaluate": (jitted["evaluate"], (actors, eval_key))})
        return cls(agent, seeds, futures)

    def __getitem__(self, name: str):
        """The compiled program `name`, waiting for its compilation if needed."""
        return self.futures[name].result()


_JITTED: "weakref.WeakKeyDictionary[Agent, dict]" = weakref.WeakKeyDictionary()


def _jitted(agent: Agent, seeds: bool, sharding: Optional[jax.sharding.Sharding]) -> dict:
    """The agent's jitted programs, made once per agent, seeds and sharding: a later run of
    the same agent in this process (`make_agent` returns one agent per configuration) finds
    their traces and executables in JAX's caches instead of tracing the physics again."""
    per_agent = _JITTED.setdefault(agent, {})
    if (seeds, sharding) not in per_agent:
        batched = jax.vmap if seeds else (lambda fn: fn)
        jit = (jax.jit if sharding is None
               else functools.partial(jax.jit, out_shardings=sharding))
        per_agent[seeds, sharding] = {
            "init": jit(batched(agent.init)),
            "play": jit(batched(agent.play), donate_argnums=0),
            "learn": jit(batched(agent.learn), donate_argnums=0),
            "evaluate": jit(batched(agent.evaluate)),
            "evaluated_actors": batched(agent.evaluated_actors)}
    return per_agent[seeds, sharding]


def placed(shapes, sharding: Optional[jax.sharding.Sharding]):
    """`shapes` (ShapeDtypeStructs) with every array placed by `sharding`, if given."""
    if sharding is None:
        return shapes
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding),
                        shapes)


@dataclasses.dataclass(frozen=True)
class Generation:
    """What one generation reports, on the host."""

    metrics: dict
    """`learn`'s metrics (`pgps_jax.agent.metrics`), as numpy values."""
    seconds: float
    play_seconds: Optional[float] = None
    """Time to the end of `play` (only when the phases were timed apart)."""


def generation(programs: Programs, state: TrainState,
               time_phases: bool = False) -> tuple[TrainState, Generation]:
    """One generation: `play`, then `learn`, with the metrics fetched. `time_phases` waits for
    `play` to end before `learn` starts (one wait more, to time the phases apart)."""
    start = time.perf_counter()
    state, played = programs["play"](state)
    played_at = None
    if time_phases:
        jax.block_until_ready(played)
        played_at = time.perf_counter() - start
    state, metrics = programs["learn"](state, played)
    metrics = jax.device_get(metrics)
    return state, Generation(metrics, time.perf_counter() - start, played_at)


@dataclasses.dataclass(frozen=True)
class Finished:
    """The evaluations that end a run (host values; a leading seed axis with `seeds`)."""

    unfinished: Optional[dict]
    """The evaluation that was under way, played to its end from its start (`evaluate`
    metrics), or None where none was; see `unfinished_active`."""
    unfinished_active: np.ndarray
    """[] or [S] bool: an evaluation was under way (of that seed)."""
    unfinished_step: np.ndarray
    """[] or [S] env steps at which it began."""
    final: dict
    """The final evaluation: of the actors of the state the run ends with, or of those given."""


def finish(programs: Programs, state: TrainState, final_key: Optional[jax.Array] = None,
           final_actors: Optional[jax.Array] = None) -> tuple[TrainState, Finished]:
    """Ends a run's evaluations: the one under way, played from its start to its end, and one
    of the final state's actors, or of `final_actors` where given (start states of
    `final_key`, by default the run's evaluation key). Returns the state with no evaluation
    under way."""
    agent, evaluate = programs.agent, programs["evaluate"]
    tests = state.evaluation
    active, began = jax.device_get((tests.active, tests.step))
    unfinished = (jax.device_get(evaluate(tests.actors, tests.key)) if np.any(active)
                  else None)
    actors = final_actors
    if actors is None:
        actors = (jax.vmap(agent.evaluated_actors) if programs.seeds
                  else agent.evaluated_actors)(state)
    final = jax.device_get(evaluate(actors, tests.key if final_key is None else final_key))
    state = state.replace(evaluation=tests.replace(active=jnp.zeros_like(tests.active)))
    return state, Finished(unfinished, np.asarray(active), np.asarray(began), final)

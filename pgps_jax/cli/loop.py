"""The training loop of the CLI and the benchmarks: a run's programs, its generations and the
evaluations that end it, for one seed or a batch of seeds (vmapped).

`Programs.compile` jits an agent's `init`, `play`, `learn` (state donated) and `evaluate` and
compiles them ahead of time side by side (`compile_ahead`); `generation` runs `play` then
`learn` and fetches the metrics in one `jax.device_get`; `finish` plays the evaluation under
way to its end from its start and evaluates the state the run ends with, both with the
`evaluate` program. A caller loops `generation` until its budget and writes what it needs.

Vmapped seeds play their generations in lockstep: a generation lasts as long as the longest
rollout and the most updates among them. With `waiting` programs, a caller can let some seeds
wait a generation out (`generation(..., active=...)`): they play no step and keep their state,
so each seed's sequence of generations is the same whichever others play beside it.
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
from pgps_jax.envs import env_batches


def state_shapes(agent: Agent, key: jax.Array, eval_key: jax.Array, seeds: bool = False):
    """The shapes and dtypes of `agent.init(key, eval_key)`'s TrainState (a checkpoint is
    restored into them), found without tracing the warm-up's physics."""
    init = agent.unfilled().init
    return jax.eval_shape(jax.vmap(init) if seeds else init, key, eval_key)


@dataclasses.dataclass(frozen=True)
class Programs:
    """A run's compiled programs (futures until compiled) and its agent."""

    agent: Agent
    seeds: bool
    """Each program takes a batch of states, keys and actors (vmapped over seeds)."""
    futures: dict[str, Future]
    waiting: bool = False
    """`play` and `learn` also take which seeds play the generation (`generation`)."""
    sharding: Optional[jax.sharding.Sharding] = None
    """Where the seeds' arrays lie."""
    generation_steps: int = 0
    """The most env steps one generation of one seed can take (its rollout's episodes × their
    step limit)."""

    @classmethod
    def compile(cls, agent: Agent, key: jax.Array, eval_key: jax.Array, seeds: bool = False,
                sharding: Optional[jax.sharding.Sharding] = None, restored=None,
                waiting: bool = False) -> "Programs":
        """Starts compiling: `init` (unless `restored`) with `play` and `learn` side by side,
        then `evaluate` in the background. `key`, `eval_key`: as `init` takes them (with a
        leading seed axis if `seeds`). `sharding`: where every array of the state and of a
        generation lies (a batch of seeds split over devices); by default on one device.
        `restored`: the shapes of a state restored from a checkpoint (`state_shapes`), for a
        resumed run, which needs no `init`. `waiting` (with `seeds`): `play` and `learn` take
        which seeds play each generation."""
        if waiting and not seeds:
            raise ValueError("waiting programs need a batch of seeds (seeds=True)")
        jitted = _jitted(agent, seeds, sharding)
        # A fresh run's init is traced once: `lower` reuses the trace.
        abstract = placed(jax.eval_shape(jitted["init"], key, eval_key) if restored is None
                          else restored, sharding)
        if waiting:
            active = placed(jax.ShapeDtypeStruct(abstract.generation.shape, bool), sharding)
            played = placed(jax.eval_shape(jitted["play_waiting"], abstract, active),
                            sharding)
            programs = {"play": (jitted["play_waiting"], (abstract, active)),
                        "learn": (jitted["learn_waiting"], (*played, active))}
        else:
            played = placed(jax.eval_shape(jitted["play"], abstract), sharding)
            programs = {"play": (jitted["play"], (abstract,)),
                        "learn": (jitted["learn"], played)}
        episodes = played[1].episodes.lengths.shape[-1]
        if restored is None:
            programs["init"] = (jitted["init"], (key, eval_key))
        actors = placed(jax.eval_shape(jitted["evaluated_actors"], abstract), sharding)
        futures = compile_ahead(programs, later={
            "evaluate": (jitted["evaluate"], (actors, eval_key))})
        return cls(agent, seeds, futures, waiting, sharding,
                   generation_steps=episodes * agent.config.t_max)

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
        play_waiting, learn_waiting = _waiting(agent)
        per_agent[seeds, sharding] = {
            "init": jit(batched(agent.init)),
            "play": jit(batched(agent.play), donate_argnums=0),
            "learn": jit(batched(agent.learn), donate_argnums=0),
            "play_waiting": jit(batched(play_waiting), donate_argnums=0),
            "learn_waiting": jit(batched(learn_waiting), donate_argnums=0),
            "evaluate": jit(batched(agent.evaluate)),
            "evaluated_actors": batched(agent.evaluated_actors)}
    return per_agent[seeds, sharding]


def _waiting(agent: Agent):
    """`play` and `learn` of one seed that plays the generation only if `active`: otherwise it
    plays no step and keeps its state (every part is taken back but the replay buffer, which
    a generation without steps leaves as it was)."""
    def kept_unless(active, new: TrainState, old: TrainState) -> TrainState:
        merged = env_batches.select(active, new.replace(buffer=None), old.replace(buffer=None))
        return merged.replace(buffer=new.buffer)

    def play(state: TrainState, active: jax.Array):
        new, played = agent.play(state, active)
        return kept_unless(active, new, state), played

    def learn(state: TrainState, played, active: jax.Array):
        new, metrics = agent.learn(state, played)
        return kept_unless(active, new, state), metrics
    return play, learn


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


def generation(programs: Programs, state: TrainState, time_phases: bool = False,
               active: Optional[np.ndarray] = None) -> tuple[TrainState, Generation]:
    """One generation: `play`, then `learn`, with the metrics fetched. `time_phases` waits for
    `play` to end before `learn` starts (one wait more, to time the phases apart). `active`
    [S] bool (`waiting` programs only, by default every seed): the seeds that play it; the
    others' metrics are those of a generation that did not happen."""
    waiting = ()
    if programs.waiting:
        active = np.ones(state.generation.shape, bool) if active is None else active
        waiting = (jax.device_put(np.asarray(active, bool), programs.sharding),)
    elif active is not None:
        raise ValueError("these programs play every seed: compile them with waiting=True")
    start = time.perf_counter()
    state, played = programs["play"](state, *waiting)
    played_at = None
    if time_phases:
        jax.block_until_ready(played)
        played_at = time.perf_counter() - start
    state, metrics = programs["learn"](state, played, *waiting)
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

"""One cell of an experiment, run to its budget: its seeds vmapped in one program, split over
every visible device, checkpointed so that a cut-off cell continues where it stopped.

Seed k of a cell has the keys of `python -m pgps_jax.train env=<task> seed=k` with the cell's
configuration: PRNGKey(k), evaluations from PRNGKey(k + 100) (vmapped, its arithmetic may
differ from the single run's in the last bits, and the runs drift apart). The seeds form one batch
(`pgps_jax.cli.loop`, `seeds=True`) whose leading axis is sharded over a one-axis device mesh
(`seeds`); a batch that does not divide evenly is padded with the next seeds, which never
play. One host: the loop fetches each generation's metrics to this process.

The seeds play their generations side by side, and a generation lasts as long as its longest
rollout and its most updates. A seed's generations are as long as its episodes: on a task
whose episodes end early, some seeds get ahead in env steps. A seed more than one
generation's steps (`Programs.generation_steps`) ahead of the furthest-behind, or at its
budget, waits (`playing_seeds`): it plays no step and keeps its state, so its generations
are the same as in lockstep and no seed trains past its budget. `result.json` gives the env
steps of the state each seed's final evaluation tested.

A cell's folder holds, per seed, `seed<k>.csv`: its test evaluations up to the budget in the
authors' format (Step, Mean, Std, Reward1..RewardE of the actor the algorithm reports: μ, or
TD3's actor for TD3 alone; the columns of a training run's `eval.csv`), the same of each other
evaluated actor in `seed<k>_<actor>.csv` (PGPS: the TD3 actor's and the elite's, Figure 5),
and `seed<k>_generations.csv`: per generation, the sequential env steps of its rollout and
the return of every slot of the population (Figure 6: the Q-filtered slots against the
sampled ones); `generation_times.csv`: per generation of the program, the seconds of its
play and learn phases and its rollout's sequential steps (the most of its seeds');
`result.json` once the cell is done (the final evaluation of every evaluated actor on fresh
start states PRNGKey(k + 10,000), the settings, the wall-clock, its parts outside the
generations, `WALL_SPLIT`, and the device); and `checkpoints/` while it runs, written every
`Budget.checkpoint_every_s` seconds (and every `Budget.checkpoint_every` generations where
given) and when SIGINT or SIGTERM stops it (after the generation under way). A cell is
counted as done only under the settings it was started with, its number of seeds and devices
aside, and continued from a checkpoint only under those it was started with, seeds and devices
included.

A cell's seeds can also run in parts (`Budget.seeds_per_program`): each part a program of its
own, its seeds keyed as in the whole cell, so the parts can run in turn or side by side in
processes of their own (`side_by_side`). A part writes its seeds' files, and its checkpoints,
at-budget record and result under its own names (`Seeds.suffix`); once every part is done,
`result.json` merges theirs (seeds in order, `wall_s` the sum of the parts' wall-clocks,
`device` the parts' devices, `parts` each part's own). A done cell given more seeds
(`Budget.seeds`) runs the others as parts after the seeds it has, which keep their files
(`parts(budget, done)`).
"""

import dataclasses
import json
import math
import pathlib
import shutil
import time
from typing import Callable, Collection, Optional

import jax
import jax.numpy as jnp
import numpy as np

from pgps_jax.agent.algorithms import make_agent
from pgps_jax.agent.config import (EvaluationConfig, PGPSConfig, effective_fields, for_task,
                                   saved_fields_as_run)
from pgps_jax.agent.metrics import Metric, population_return_key, returns_key
from pgps_jax.cli import loop
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli import checkpoint
from pgps_jax.cli.checkpoint import Checkpoints
from pgps_jax.cli.errors import UsageError
from pgps_jax.cli.stop_request import StopRequest
from pgps_jax.envs import make_env
from pgps_jax.envs.mjx_env import MjxEnv
from pgps_jax.experiments.paper.grid import Cell

RESULT = "result.json"
AT_BUDGET = "at_budget.npz"
CHECKPOINTS = "checkpoints"
PART = "_seeds"
"""What a part's own files add to the cell's names, before its seeds' span."""
GENERATION_TIMES = "generation_times.csv"
TIMES_COLUMNS = ["generation", "play_s", "learn_s", "rollout_steps"]
"""`GENERATION_TIMES`' columns: the seconds of a generation's phases and its rollout's
sequential env steps, the most that one of the program's seeds played."""
FILES_EVERY_S = 60.0
"""Seconds between writes of a running cell's curves and per-generation files besides those
at its checkpoints: a cell cut off between checkpoints keeps its curves to within this."""
WALL_SPLIT = ("compile", "checkpoints", "files", "final_evaluation")
"""The parts of a cell's wall-clock outside its generations (`result.json`'s `wall_split_s`,
seconds): until the first generation can start (compiling the programs, and running a fresh
cell's `init` or reading a continued cell's checkpoint), writing checkpoints, writing the
curves and per-generation files, and the final evaluation. The generations' own seconds are in
`GENERATION_TIMES`."""
FINAL_KEY_OFFSET = 10_000
"""Seed k's final evaluation starts from PRNGKey(k + FINAL_KEY_OFFSET): states no evaluation
during training saw."""


@dataclasses.dataclass(frozen=True)
class Budget:
    """How far and how each cell runs."""

    steps: int = 1_000_000
    """Env steps of every seed (the warm-up included)."""
    seeds: int = 5
    """Seeds 1..seeds."""
    evaluation: EvaluationConfig = EvaluationConfig()
    checkpoint_every: Optional[int] = None
    """Generations between checkpoints, besides `checkpoint_every_s`; None: by time alone."""
    checkpoint_every_s: float = 120.0
    """Seconds between checkpoints: a cut-off cell loses at most this much of its run (and the
    generation under way). A checkpoint writes the whole replay buffer, on walker2d 168 MB per
    seed (0.4–1.0 s on a 2-core CPU)."""
    overrides: tuple = ()
    """(field, value) pairs of PGPSConfig replacing every cell's (e.g. reduced sizes)."""
    env: tuple = ()
    """(name, value) keyword arguments of `make_env` for every cell (e.g. physics settings)."""
    seeds_per_program: Optional[int] = None
    """Seeds vmapped in one program; a cell of more runs in parts (`parts`). None: all."""


@dataclasses.dataclass(frozen=True)
class Seeds:
    """Seeds first..first + count − 1 of a cell: those one program runs."""

    first: int
    count: int
    whole: bool
    """The part is the whole cell (its files keep the cell's names)."""

    @property
    def last(self) -> int:
        return self.first + self.count - 1

    @property
    def numbers(self) -> range:
        return range(self.first, self.last + 1)

    @property
    def suffix(self) -> str:
        """What a part's own files add to their names: `_seeds<first>-<last>`, none for the
        whole cell."""
        return "" if self.whole else f"{PART}{self.first}-{self.last}"


def whole_cell(budget: Budget) -> Seeds:
    """All of a cell's seeds, in one program."""
    return Seeds(1, budget.seeds, whole=True)


def parts(budget: Budget, done: int = 0) -> list[Seeds]:
    """The parts a cell's seeds run in: `seeds_per_program` at a time, the last holding the
    rest. A cell whose `result.json` holds seeds 1..`done` (`done_seeds`), fewer than the
    budget's, is given the others: its seeds so far are one part, under the cell's names, and
    the rest follow it, `seeds_per_program` at a time or all in one program."""
    if done >= budget.seeds:
        return [whole_cell(budget)]
    size = budget.seeds_per_program or budget.seeds - done
    if done == 0 and size >= budget.seeds:
        return [whole_cell(budget)]
    given = [Seeds(1, done, whole=True)] if done else []
    return given + [Seeds(first, min(size, budget.seeds - first + 1), whole=False)
                    for first in range(done + 1, budget.seeds + 1, size)]


def done_seeds(directory: pathlib.Path) -> int:
    """How many seeds (1..m) the cell in `directory` has done: those of its `result.json`."""
    path = directory / RESULT
    return len(json.loads(path.read_text())["seeds"]) if path.exists() else 0


def _split(budget: Budget, done: int) -> list[Seeds]:
    """The parts whose files a cell with seeds 1..`done` done holds under `budget`: those of
    a done cell given more seeds (`parts(budget, done)`), else `parts(budget)`."""
    return parts(budget, done if done < budget.seeds else 0)


def seed_file(seed: int, actor: str = "") -> str:
    """The curve of seed `seed`: the reported actor's (`actor` empty) in `seed<k>.csv`, another
    evaluated actor's in `seed<k>_<actor>.csv`."""
    return f"seed{seed}_{actor}.csv" if actor else f"seed{seed}.csv"


def generations_file(seed: int) -> str:
    """Seed `seed`'s per-generation metrics (`_population_metrics`)."""
    return f"seed{seed}_generations.csv"


def seed_mesh() -> jax.sharding.Mesh:
    """A one-axis mesh (`seeds`) over every visible device."""
    return jax.make_mesh((len(jax.devices()),), ("seeds",),
                         axis_types=(jax.sharding.AxisType.Auto,))


def padded_seeds(seeds: int, devices: int) -> int:
    """The batch: `seeds` rounded up to a multiple of the devices."""
    return math.ceil(seeds / devices) * devices


def playing_seeds(steps: np.ndarray, budget: Budget, lead: int, seeds: int) -> np.ndarray:
    """[batch] bool: which of the program's `seeds` (the rest of its batch pads it) play the
    next generation. Those below the budget play unless more than `lead` env steps ahead of
    the furthest-behind of them; the others, and the padding seeds, wait."""
    below = np.zeros(steps.shape, bool)
    below[:seeds] = steps[:seeds] < budget.steps
    if not below.any():
        return below
    return below & (steps <= steps[below].min() + lead)


def seed_lock(seed: int) -> str:
    """The file locked by the process that runs `seed` of a cell (whole or in a part) while it
    runs; removed when it stops, unless killed."""
    return f"running_seed{seed}.lock"


def part_file(name: str, part: Seeds) -> str:
    """A part's own file of the cell's file `name` (`RESULT`, `AT_BUDGET`, `CHECKPOINTS`,
    `GENERATION_TIMES`): the same for the whole cell."""
    stem, dot, extension = name.partition(".")
    return f"{stem}{part.suffix}{dot}{extension}"


def run_cell(cell: Cell, directory: pathlib.Path, budget: Budget,
             on_generation: Optional[Callable[[int, np.ndarray], None]] = None,
             part: Optional[Seeds] = None) -> dict:
    """Runs `cell` to `budget.steps` in `directory` (continuing its checkpoint if it has one)
    and returns its result (as `result.json` holds it); with `part` (one of `parts(budget,
    done_seeds(directory))`), only those seeds, returning the part's result (the cell's,
    where the cell was done whole) and merging every part's into the cell's once all are
    done. A done cell or part is not run again; a part whose cell holds parts or checkpoints
    of other settings or of another split is refused. `on_generation(generation, env_steps
    [the part's seeds])` is called after every generation. Each seed runs in one process at
    a time: one given a seed that another is running, in the whole cell or a part, is refused
    (`seed_lock`)."""
    seeds_done = done_seeds(directory)
    if part is None and 0 < seeds_done < budget.seeds:
        raise UsageError(f"{directory} holds this cell done with {seeds_done} seeds; run the "
                         "others as parts(budget, done)")
    part = part or whole_cell(budget)
    config = for_task(cell.task, cell.algo, **dict(cell.overrides), **dict(budget.overrides))
    mesh = seed_mesh()
    env = make_env(cell.task, **dict(budget.env))
    settings = _settings(cell.algo, config, budget, mesh.size, env)
    with rundir.writing(directory):
        directory.mkdir(parents=True, exist_ok=True)
    locks = []
    try:
        for seed in part.numbers:
            locks.append(rundir.RunLock(directory / seed_lock(seed), busy=f"seed {seed} runs "
                                        "there; wait for it to finish or stop it, or give "
                                        "another --out"))
        return _run_part(cell, directory, budget, part, config, env, settings, mesh,
                         on_generation)
    finally:
        for lock in locks:
            lock.release(remove=True)


def _run_part(cell: Cell, directory: pathlib.Path, budget: Budget, part: Seeds,
              config: PGPSConfig, env: MjxEnv, settings: dict, mesh: jax.sharding.Mesh,
              on_generation: Optional[Callable[[int, np.ndarray], None]]) -> dict:
    """`run_cell`'s work on `part` of `cell`, under its seeds' locks."""
    for done in dict.fromkeys((part_file(RESULT, part), RESULT)):
        if (directory / done).exists():
            result = json.loads((directory / done).read_text())
            _require_same(directory, result["settings"], settings, cell.task, done=True)
            if not set(part.numbers) <= set(result["seeds"]):
                continue  # the cell's result, of fewer seeds than it is now given
            if not part.whole:
                merge_parts(directory, budget, settings, cell.task)
            return result
    _require_parts_alike(directory, budget, settings, cell.task)
    agent = make_agent(cell.algo, config, env, budget.evaluation)
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("seeds"))
    batch = padded_seeds(part.count, mesh.size)
    numbers = jnp.arange(part.first, part.first + batch)
    keys = jax.device_put(jax.vmap(jax.random.PRNGKey)(numbers), sharding)
    eval_keys = jax.device_put(jax.vmap(jax.random.PRNGKey)(numbers + 100), sharding)
    at_budget_file = directory / part_file(AT_BUDGET, part)
    population_keys = [m.key for m in _population_metrics(agent)]
    start = time.perf_counter()
    checkpoints = Checkpoints(directory / part_file(CHECKPOINTS, part), keep=2)
    try:
        if checkpoints.latest_step() is None:
            at_budget_file.unlink(missing_ok=True)  # an earlier run's, whose checkpoints went
            programs = loop.Programs.compile(agent, keys, eval_keys, seeds=True,
                                             sharding=sharding, waiting=True)
            state = programs["init"](keys, eval_keys)
            generation, elapsed = 0, 0.0
            curves = {actor: [[] for _ in range(batch)] for actor in agent.evaluated}
            populations, times = [[] for _ in range(batch)], []
            split = dict.fromkeys(WALL_SPLIT, 0.0)
        else:
            meta = checkpoints.latest_meta()[1]
            _require_same(directory, meta["settings"], settings, cell.task)
            older = _older_runner(meta, len(population_keys))
            if older:
                raise UsageError(f"{checkpoints.directory} was written by an older runner "
                                 f"({older}); remove it to run the cell again")
            shapes = loop.placed(loop.state_shapes(agent, keys, eval_keys, seeds=True),
                                 sharding)
            generation, state, meta = checkpoints.restore_latest(shapes)
            curves, populations = meta["curves"], meta["populations"]
            times = meta.get("times", [])
            elapsed = meta["elapsed_s"]
            split = {**dict.fromkeys(WALL_SPLIT, 0.0), **meta.get("wall_split_s", {})}
            programs = loop.Programs.compile(agent, keys, eval_keys, seeds=True,
                                             sharding=sharding, restored=shapes,
                                             waiting=True)
        programs.futures["play"].result(), programs.futures["learn"].result()  # as generation 1
        steps = np.asarray(jax.device_get(state.total_steps))
        split["compile"] += time.perf_counter() - start
        at_budget = AtBudget.read(at_budget_file, part.count, generation)
        at_budget.record(generation, steps, state, agent, budget, at_budget_file)
        written = checkpointed = time.perf_counter()
        saved = generation

        def write_files():
            began = time.perf_counter()
            _write_files(directory, curves, populations, times, agent, budget, part)
            split["files"] += time.perf_counter() - began

        def save():
            began = time.perf_counter()
            checkpoints.save(generation, state, {
                "settings": settings, "curves": curves, "populations": populations,
                "times": times, "elapsed_s": elapsed + began - start, "wall_split_s": split})
            split["checkpoints"] += time.perf_counter() - began
            write_files()
            return generation, time.perf_counter()
        with StopRequest() as stop:
            while steps[:part.count].min() < budget.steps and stop.requested is None:
                active = playing_seeds(steps, budget, programs.generation_steps, part.count)
                state, done = loop.generation(programs, state, time_phases=True, active=active)
                generation += 1
                m = done.metrics
                times.append([generation, done.play_seconds, done.seconds - done.play_seconds,
                              int(m["gen/rollout_steps"][active].max())])
                for seed in np.flatnonzero(m["eval/done"] & active):
                    _add_evaluation(curves, m, seed, int(m["eval/step"][seed]))
                for seed in np.flatnonzero(active):
                    populations[seed].append([int(m["gen/generation"][seed])] + [
                        np.asarray(m[key][seed]).item() for key in population_keys])
                steps = np.where(active, m["gen/total_steps"], steps)
                at_budget.record(generation, steps, state, agent, budget, at_budget_file)
                if checkpoint.due(generation, budget.checkpoint_every, budget.checkpoint_every_s,
                                  time.perf_counter() - checkpointed):
                    saved, written = save()
                    checkpointed = written
                elif time.perf_counter() - written >= FILES_EVERY_S:
                    write_files()
                    written = time.perf_counter()
                if on_generation is not None:
                    on_generation(generation, steps[:part.count])
            if stop.requested is not None and steps[:part.count].min() < budget.steps:
                if saved != generation:
                    save()
                raise KeyboardInterrupt  # the command says how to continue
            began = time.perf_counter()
            final_keys = jax.device_put(
                jax.vmap(jax.random.PRNGKey)(numbers + FINAL_KEY_OFFSET), sharding)
            state, finished = loop.finish(programs, state, final_keys,
                                          at_budget.actors_of(state, agent, sharding))
            split["final_evaluation"] += time.perf_counter() - began
    finally:
        checkpoints.close()
        if checkpoints.directory.is_dir() and not any(checkpoints.directory.iterdir()):
            checkpoints.directory.rmdir()  # stopped before its first checkpoint
    for seed in np.flatnonzero(finished.unfinished_active):  # played from its start
        _add_evaluation(curves, finished.unfinished, seed, int(finished.unfinished_step[seed]))
    write_files()
    result = {"task": cell.task, "config": cell.config, "algo": cell.algo,
              "overrides": dict(cell.overrides),
              "steps": budget.steps, "seeds": list(part.numbers),
              "env_steps": at_budget.steps.tolist(), "generations": generation,
              "final": {actor: np.asarray(finished.final[f"eval/{actor}_mean"])
                        [:part.count].tolist() for actor in agent.evaluated},
              "wall_s": elapsed + time.perf_counter() - start, "wall_split_s": split,
              "device": f"{mesh.size} × {jax.devices()[0].device_kind}", "settings": settings}
    rundir.write_atomic(directory / part_file(RESULT, part), json.dumps(result, indent=1).encode())
    shutil.rmtree(checkpoints.directory, ignore_errors=True)  # the result is all it keeps
    at_budget_file.unlink(missing_ok=True)
    if not part.whole:
        merge_parts(directory, budget, settings, cell.task)
    if stop.requested is not None:  # in its last generation: done, and nothing more runs
        raise KeyboardInterrupt
    return result


def _require_parts_alike(directory: pathlib.Path, budget: Budget, settings: dict,
                         task: str) -> None:
    """UsageError unless every part's result in `directory` was run under `settings`, and
    every checkpoint there, and every done part whose seeds the cell's `RESULT` does not hold
    yet, is of one of the parts of `budget`'s split (a cell cut off in another split
    continues only in that split)."""
    merged = done_seeds(directory)
    split = _split(budget, merged)
    stem, _, extension = RESULT.partition(".")
    our_results = {part_file(RESULT, part) for part in split}
    stray_results = []
    for done in sorted(directory.glob(f"{stem}{PART}*.{extension}")):
        result = json.loads(done.read_text())
        _require_same(directory, result["settings"], settings, task, done=True)
        if done.name not in our_results and max(result["seeds"]) > merged:
            stray_results.append(done.name)
    if stray_results:
        raise UsageError(f"{directory} holds parts of this cell done in another split "
                         f"({', '.join(stray_results)}); continue it with the --seeds and "
                         "--seeds-per-program it was started with, or remove them to run "
                         "their seeds again")
    our_checkpoints = {part_file(CHECKPOINTS, part) for part in split}
    stray_checkpoints = sorted(p.name for p in directory.glob(f"{CHECKPOINTS}*")
                               if p.name not in our_checkpoints and any(p.iterdir()))
    if stray_checkpoints:
        whole = "whole" if CHECKPOINTS in stray_checkpoints else "in parts"
        raise UsageError(f"{directory} holds checkpoints of this cell run {whole} "
                         f"({', '.join(stray_checkpoints)}); continue it with the --seeds and "
                         "--seeds-per-program it was started with, or remove them to run "
                         "it again")


def merge_parts(directory: pathlib.Path, budget: Budget, settings: dict, task: str) -> None:
    """Writes the cell's `RESULT` from its parts' (`parts`; a done cell given more seeds:
    its `RESULT` so far and the parts after it) once every part is done (UsageError if one
    was run under other settings than `settings`)."""
    cell_result = directory / RESULT
    given = json.loads(cell_result.read_text()) if cell_result.exists() else None
    files = [directory / part_file(RESULT, part)
             for part in _split(budget, len(given["seeds"]) if given else 0)]
    if len(files) == 1 or not all(f.exists() for f in files):
        return
    done = [given if f == cell_result else json.loads(f.read_text()) for f in files]
    for result in done:
        _require_same(directory, result["settings"], settings, task, done=True)
    merged = {**done[0], "seeds": [s for d in done for s in d["seeds"]],
              "env_steps": [s for d in done for s in d["env_steps"]],
              "generations": max(d["generations"] for d in done),
              "final": {actor: [v for d in done for v in d["final"][actor]]
                        for actor in done[0]["final"]},
              "wall_s": sum(d["wall_s"] for d in done),
              "settings": {**done[0]["settings"], "seeds": budget.seeds},
              "parts": [part for d in done for part in d.get("parts", [
                  {key: d[key] for key in ("seeds", "generations", "wall_s", "wall_split_s",
                                           "device") if key in d}])]}
    devices = dict.fromkeys(part["device"] for part in merged["parts"] if "device" in part)
    if devices:  # the parts ran on these, each named once
        merged["device"] = "; ".join(devices)
    if all("wall_split_s" in d for d in done):  # results from before it have none
        merged["wall_split_s"] = {key: sum(d["wall_split_s"][key] for d in done)
                                  for key in WALL_SPLIT}
    else:
        merged.pop("wall_split_s", None)
    rundir.write_atomic(directory / RESULT, json.dumps(merged, indent=1).encode())


@dataclasses.dataclass
class AtBudget:
    """Each seed's evaluated actors [A, P], env steps and generation when it first reached
    the budget.

    A seed's final evaluation is of its actors at its own budget, as its curve ends there.
    A seed at its budget waits (`playing_seeds`), so these are its final state's actors; the
    record also serves a cell continued from a checkpoint written while seeds still trained
    past their budget. Kept in the cell's `AT_BUDGET` file (a part's: `at_budget<suffix>.npz`)
    for a cut-off cell: a cell
    continued from its checkpoint at generation g keeps the records of generations up to g
    and makes the later ones again from its replayed generations (which a GPU need not replay
    bit for bit)."""

    actors: list
    """Per seed: its actors (numpy), or None while it is below the budget."""
    steps: np.ndarray
    """[seeds] env steps when reached (0 while below)."""
    generations: np.ndarray
    """[seeds] the generation after which it was reached (-1 while below)."""

    @classmethod
    def read(cls, path: pathlib.Path, seeds: int, generation: int) -> "AtBudget":
        """The records in `path` of generations up to `generation` (the one the cell
        continues from), of a program of `seeds` seeds."""
        kept = cls([None] * seeds, np.zeros(seeds, np.int64), np.full(seeds, -1, np.int64))
        if path.exists():
            with np.load(path) as saved:
                for i in np.flatnonzero((saved["generations"] >= 0)
                                        & (saved["generations"] <= generation)):
                    kept.actors[i] = saved[f"seed{i + 1}"]
                    kept.steps[i], kept.generations[i] = (saved["steps"][i],
                                                          saved["generations"][i])
        return kept

    def record(self, generation: int, steps: np.ndarray, state, agent, budget,
               path: pathlib.Path) -> None:
        """Records the seeds that have reached the budget since the last call, in `path`."""
        reached = [i for i in range(len(self.actors))
                   if self.actors[i] is None and steps[i] >= budget.steps]
        if not reached:
            return
        actors = np.asarray(jax.device_get(jax.vmap(agent.evaluated_actors)(state)))
        for i in reached:
            self.actors[i], self.steps[i], self.generations[i] = actors[i], steps[i], generation
        arrays = {f"seed{i + 1}": a for i, a in enumerate(self.actors) if a is not None}
        rundir.write_npz(path, steps=self.steps,
                         generations=self.generations, **arrays)

    def actors_of(self, state, agent, sharding) -> jax.Array:
        """[batch, A, P]: the recorded actors; the padding seeds' current ones."""
        current = np.array(jax.device_get(jax.vmap(agent.evaluated_actors)(state)))
        for i, actors in enumerate(self.actors):
            current[i] = actors
        return jax.device_put(current, sharding)


def env_physics(env) -> Optional[dict]:
    """The physics an env simulates (`MjxEnv.settings`); None for an env without MJX physics
    (the point mass)."""
    return env.settings() if isinstance(env, MjxEnv) else None


def _settings(algo: str, config, budget: Budget, devices: int, env) -> dict:
    """What a cell's results depend on (JSON values), the env's physics included."""
    physics = env_physics(env)
    return json.loads(json.dumps({
        "algo": algo, "config": dataclasses.asdict(config),
        "evaluation": dataclasses.asdict(budget.evaluation), "env": dict(budget.env),
        "physics": physics, "steps": budget.steps, "seeds": budget.seeds,
        "devices": devices}))


_ADDED_SETTINGS = {"env": {}, "algo": "pgps"}
"""Settings that cells started before they existed ran under."""
_PHYSICS_BEFORE_RECORDED = {"halfcheetah": {"iterations": 1}, "walker2d": {"iterations": 1},
                            "ant": {"iterations": 2, "ls_iterations": 4}}
"""The fields in which a task's physics differed from today's when cells did not record it
yet (the Newton iterations of halfcheetah, walker2d and ant, and the ant's line search; the
ant's results from before its Gym physics are not cells)."""


_PHYSICS_FIELDS_ADDED = {"impl": "jax", "matmul_precision": "default"}
"""Physics settings that cells recorded before they existed ran under."""


def physics_of(settings: dict, task: str) -> Optional[dict]:
    """The physics a cell's results were computed on (`MjxEnv.settings`; None for an env
    without MJX physics): as its settings record it (fields added since at
    `_PHYSICS_FIELDS_ADDED`), or, for a cell from before they did, the task's physics of then
    with the cell's `--env` arguments."""
    if "physics" in settings:
        recorded = settings["physics"]
        return None if recorded is None else {**_PHYSICS_FIELDS_ADDED, **recorded}
    today = env_physics(make_env(task))
    if today is None:
        return None
    then = {**today, **_PHYSICS_FIELDS_ADDED, **_PHYSICS_BEFORE_RECORDED.get(task, {})}
    return {**then, **{k: v for k, v in settings.get("env", {}).items() if k in then}}


def settings_differing(saved: dict, now: dict, env_key: str,
                       ignored: Collection[str] = ()) -> list[str]:
    """The settings of `now`, in its order and except those in `ignored`, that `saved` holds
    with other values or not at all. The `--env` arguments (`env_key`) count only through the
    MJX physics they give (`now["physics"]`, compared as a setting), so that those which change
    only how it is computed (`physics.SPEED_ONLY`) may differ; for an env without MJX physics
    they count as themselves."""
    skip = set(ignored) | ({env_key} if now["physics"] is not None else set())
    return [key for key in now if key not in skip and saved.get(key) != now[key]]


def _require_same(directory: pathlib.Path, saved: dict, now: dict, task: str,
                  done: bool = False) -> None:
    """UsageError naming the settings in which the cell of `task` in `directory` differs from
    `now` (the `--env` arguments count through the MJX physics they give, so that those which
    change only how it is computed, `physics.SPEED_ONLY`, do not; for a `done` cell, the
    devices its seeds were split over and the number of seeds do not count either: a cell
    continued from a checkpoint needs its batch, a result does not, and a done cell can be
    given more seeds)."""
    saved = {**_ADDED_SETTINGS, **saved, "physics": physics_of(saved, task)}
    ignored = {"config"} | ({"devices", "seeds"} if done else set())
    differ = [f"{key}: {saved.get(key)!r} there, {now[key]!r} now"
              for key in settings_differing(saved, now, "env", ignored)]
    saved_config = saved_fields_as_run(saved["config"])
    differ += [f"config.{k}: {saved_config.get(k)!r} there, {v!r} now"
               for k, v in effective_fields(now["config"]).items()
               if saved_config.get(k) != v]
    if not differ:
        return
    remedy = ("use another --out, or remove the folder to run it again" if done else
              "continue it with the settings, --seeds and devices it was started with (a "
              "part run side by side sees one GPU), or remove its checkpoints to start it "
              "again")
    raise UsageError(f"{directory} holds this cell run with other settings; {remedy}. "
                     "Differences:\n  " + "\n  ".join(differ))


def _older_runner(meta: dict, population_columns: int) -> str:
    """What marks a checkpoint's `meta` as an older runner's (empty if nothing): μ's curves
    only, or per-generation rows (`_population_metrics`, `TIMES_COLUMNS`) of other widths."""
    if not isinstance(meta["curves"], dict):
        return "μ's curves only"
    if (any(len(row) != 1 + population_columns for rows in meta["populations"] for row in rows)
            or any(len(row) != len(TIMES_COLUMNS) for row in meta.get("times", []))):
        return "other per-generation columns"
    return ""


def _population_metrics(agent) -> list[Metric]:
    """The per-generation metrics of `seed<k>_generations.csv`, after the generation number:
    env steps, episode limit, the rollout's sequential steps (a program of several seeds plays
    as many as the most of them), whether the critic chose slots [N/2, N) and the TD3 actor
    played slot N−1, the return of every slot (slot 0 the elite; Figure 6 compares the Q-filtered
    slots with the sampled ones), and what shapes the next population: the generation's
    elite and TD3 returns, the guided loss and β (eq. 3), Σ's mean and damping; those of them
    that the agent reports."""
    schema = {m.key: m for m in agent.generation_metrics()}
    keys = ["gen/total_steps", "gen/episode_limit", "gen/rollout_steps",
            "gen/q_filter_active", "td3/in_population",
            *(population_return_key(i) for i in range(agent.config.pop_size)),
            "cem/elite_return", "td3/return", "td3/guided_loss", "td3/beta", "cem/var_mean",
            "cem/damping"]
    return [schema[key] for key in keys if key in schema]


def _write_files(directory: pathlib.Path, curves: dict, populations: list, times: list,
                 agent, budget: Budget, part: Seeds) -> None:
    """The part's curves (`_write_curves`), per-generation metrics (`_write_populations`) and
    `GENERATION_TIMES`: per generation, the wall-clock seconds of its play phase (the
    rollouts, the test episodes riding along) and of its learn phase (the buffer, the CEM and
    the TD3 updates), shared by the program's seeds, and the sequential env steps of its
    rollout: as many as the seed that played the most."""
    _write_curves(directory, curves, budget, part)
    _write_populations(directory, populations, agent, part)
    rundir.write_csv(directory / part_file(GENERATION_TIMES, part), TIMES_COLUMNS, times)


def _write_populations(directory: pathlib.Path, populations: list, agent, part: Seeds) -> None:
    """seed<k>_generations.csv of every seed of the part (`_population_metrics`)."""
    header = ["generation"] + [m.column for m in _population_metrics(agent)]
    for seed, rows in zip(part.numbers, populations):
        rundir.write_csv(directory / generations_file(seed), header, rows)


def _add_evaluation(curves: dict, metrics: dict, seed: int, step: int) -> None:
    """Appends seed `seed`'s evaluation to each actor's curve: step, mean, std and the test
    returns."""
    for actor, rows in curves.items():
        returns = np.asarray(metrics[returns_key(actor)][seed])
        rows[seed].append([step, float(returns.mean()), float(returns.std()),
                           *map(float, returns)])


def _write_curves(directory: pathlib.Path, curves: dict, budget: Budget, part: Seeds) -> None:
    """The curve of every actor and seed (`seed_file`; the first actor's is the reported
    one): its evaluations so far, up to the budget, in the authors' format."""
    for index, (actor, per_seed) in enumerate(curves.items()):
        for seed, rows in zip(part.numbers, per_seed):
            rows = [row for row in rows if row[0] <= budget.steps]
            episodes = len(rows[0]) - 3 if rows else 0
            rundir.write_csv(directory / seed_file(seed, actor if index else ""),
                             rundir.eval_columns(episodes),
                             [[i, *row] for i, row in enumerate(rows)])

"""The host side of `python -m pgps_jax.train` (see `pgps_jax.cli.train`): the shared loop
(`pgps_jax.cli.loop`) with the run's logs, checkpoints and progress bar.

Each generation runs the compiled phases (`play`, then `learn` of the run's agent, the state
donated), fetches the metrics with one `jax.device_get`, then writes the logs (the columns of
`pgps_jax.agent.metrics`) and checkpoints. The test evaluation runs inside the generations,
alongside the rollouts (`pgps_jax.agent.evaluation`): it falls due whenever the env steps
have reached a multiple of `eval_every` (and in the first generation, after the warm-up),
tests the actors of the state that generation starts from, and is written, under that state's
step count, by the generation in which its episodes have ended. After the last generation,
the evaluation still under way is played to its end from its start and the final state is
evaluated, both by the agent's `evaluate` (`loop.finish`). Checkpoints are written every
`checkpoint_every_s` seconds (and every `checkpoint_every` generations where set), at the end
and on SIGINT / SIGTERM. The programs compile
ahead of time side by side (`compile_ahead`): `init` with the two phases, then `evaluate` in
the background while the run trains. Nothing here runs inside jit. The run directory's
contents are listed in `pgps_jax.cli.run_dir`.
"""

import shutil
import sys
import time
from typing import Any, Mapping, Optional

import jax
import numpy as np
from tqdm import tqdm

from pgps_jax.agent import metrics as schema
from pgps_jax.agent.algorithms import make_agent
from pgps_jax.agent.base import Agent
from pgps_jax.cli import checkpoint, loop
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.checkpoint import Checkpoints
from pgps_jax.cli.errors import RunFailed, WriteFailed
from pgps_jax.cli.plan import Plan
from pgps_jax.cli.stop_request import StopRequest

_SHORT = {"mu": "μ", "td3": "TD3", "elite": "elite"}
"""How the terminal names the evaluated actors."""

# Checked first, so the error names the loss when a NaN has spread to other metrics.
_PRIORITY_METRICS = ("td3/critic_loss", "td3/actor_loss", "td3/beta")


class NonFiniteError(RunFailed):
    """A generation produced a NaN/inf metric; the run stops without checkpointing it."""


def first_non_finite(metrics: Mapping[str, Any]) -> Optional[str]:
    """The first metric holding NaN or inf, losses first; None if all are finite. A metric
    that holds no value this generation (`schema.holds_value`) is skipped."""
    order = [k for k in _PRIORITY_METRICS if k in metrics]
    order += sorted(k for k in metrics if k not in _PRIORITY_METRICS)
    for key in order:
        if not schema.holds_value(key, metrics):
            continue
        value = np.asarray(metrics[key])
        if np.issubdtype(value.dtype, np.inexact) and not np.all(np.isfinite(value)):
            return key
    return None


class Trainer:
    """The loop's state on the host: logs, checkpoints, counters, progress bar."""

    def __init__(self, p: Plan, agent: Agent):
        self.p, self.run, self.config, self.dir = p, p.run, p.config, p.directory
        self.agent = agent
        self.reported = agent.evaluated[0]
        self.programs: Optional[loop.Programs] = None
        self.columns = agent.generation_metrics()
        self.checkpoints = Checkpoints(self.dir.checkpoints, self.run.keep_checkpoints)
        self.metrics_log = rundir.CsvLog(self.dir / rundir.METRICS,
                                         rundir.metrics_columns(self.columns))
        self.eval_log = rundir.CsvLog(self.dir / rundir.EVAL,
                                      rundir.eval_columns(agent.evaluation_config.episodes))
        self.policies_log = rundir.CsvLog(self.dir / rundir.EVAL_POLICIES,
                                          rundir.eval_policies_columns(agent.evaluated))
        self.logs = {rundir.METRICS: self.metrics_log, rundir.EVAL: self.eval_log,
                     rundir.EVAL_POLICIES: self.policies_log}
        self.tensorboard = None
        self.bar = None
        self.generation = self.total = 0
        self.elapsed_before = 0.0
        self._clock = self.checkpointed = time.perf_counter()  # again once started
        self.last_saved: Optional[int] = None
        self.eval_rows: list[dict] = []

    # --- start ------------------------------------------------------------------------
    def start(self):
        """The state to train from: a new one (after the warm-up) or a checkpoint's.

        Evaluations start from PRNGKey(seed + 100), as in the paper, every time.
        """
        seed_key, eval_key = (jax.random.PRNGKey(self.run.seed),
                              jax.random.PRNGKey(self.run.seed + 100))
        if self.p.resume_step is None:
            self.programs = loop.Programs.compile(self.agent, seed_key, eval_key)
            for log in self.logs.values():
                log.start()
            shutil.rmtree(self.dir / rundir.TENSORBOARD, ignore_errors=True)
            self.tensorboard = rundir.TensorBoard(self.dir / rundir.TENSORBOARD)
            self._open_bar()
            state = self.programs["init"](seed_key, eval_key)
            self.total = int(state.total_steps)
            self.bar.update(min(self.total, self.run.total_steps))
            self.checkpointed = time.perf_counter()  # the clock counts training, not compiling
            return state
        shapes = loop.state_shapes(self.agent, seed_key, eval_key)
        step, state, meta = self.checkpoints.restore_latest(shapes)
        if meta["total_steps"] < self.run.total_steps:  # a finished run needs no programs
            self.programs = loop.Programs.compile(self.agent, seed_key, eval_key,
                                                  restored=shapes)
        for name, log in self.logs.items():
            log.reopen(meta["logs"][name])
        self.generation, self.total = meta["generation"], meta["total_steps"]
        self.elapsed_before = meta["elapsed_s"]
        self.last_saved = step
        self.tensorboard = rundir.TensorBoard(self.dir / rundir.TENSORBOARD,
                                              purge_step=self.total + 1)
        self.eval_rows = self.policies_log.rows()
        actors = self.dir / rundir.ACTORS
        if not actors.exists() or rundir.load_actors(actors)["generation"] != self.generation:
            self.save_actors(state)  # a later checkpoint's were saved, then set aside
        self._open_bar()
        tqdm.write(f"resumed {self.dir.path} at generation {self.generation} "
                   f"({self.total:,} env steps)")
        self.checkpointed = time.perf_counter()
        return state

    def _open_bar(self):
        self.bar = tqdm(total=self.run.total_steps, initial=min(self.total, self.run.total_steps),
                        unit="step", unit_scale=True, dynamic_ncols=True, smoothing=0.3,
                        disable=not self.run.progress,
                        desc=f"{self.run.algo} {self.run.env} seed {self.run.seed}")
        self.bar.set_postfix_str(self._last_eval_text(), refresh=False)

    def elapsed(self) -> float:
        """Seconds of training, over all sessions of this run."""
        return self.elapsed_before + time.perf_counter() - self._clock

    # --- one generation ---------------------------------------------------------------
    def step(self, state):
        """One generation, its logs, and the evaluation / checkpoint when due."""
        state, done_generation = loop.generation(self.programs, state)
        m = done_generation.metrics
        previous = self.total
        self.generation, self.total = int(m["gen/generation"]), int(m["gen/total_steps"])
        steps_per_s = int(m["gen/interaction_steps"]) / done_generation.seconds
        self.metrics_log.write([m[c.key] for c in self.columns] + [steps_per_s, self.elapsed()])
        members = {schema.population_return_key(i) for i in range(self.config.pop_size)}
        self.tensorboard.scalars(
            {**{c.key: m[c.key] for c in self.columns
                if c.key not in members and schema.holds_value(c.key, m)},
             "perf/steps_per_s": steps_per_s}, self.total)
        bad = first_non_finite(m)
        if bad is not None:
            raise NonFiniteError(
                f"generation {self.generation} ({self.total:,} env steps) produced a "
                f"non-finite {bad} = {np.asarray(m[bad])}; stopping. This state was not "
                f"checkpointed; {self.kept()}.")
        if bool(m["eval/done"]):
            self._record_evaluation(int(m["eval/step"]), m)
        budget = self.run.total_steps
        self.bar.set_postfix_str(f"gen {self.generation}, T {int(m['gen/episode_limit'])}, "
                                 + self._last_eval_text(), refresh=False)
        self.bar.update(min(self.total, budget) - min(previous, budget))
        done = self.total >= budget
        if done:
            state = self.final_evaluation(state)
        if done or checkpoint.due(self.generation, self.run.checkpoint_every,
                                  self.run.checkpoint_every_s,
                                  time.perf_counter() - self.checkpointed):
            self.save(state)
        return state

    def final_evaluation(self, state):
        """Plays the evaluation under way to its end, then evaluates the state the run ends
        with (no later generation will do either). Returns the state, its evaluation ended."""
        state, finished = loop.finish(self.programs, state)
        if finished.unfinished is not None:
            self._record_evaluation(int(finished.unfinished_step), finished.unfinished)
        self._record_evaluation(self.total, finished.final)
        return state

    def _last_eval_text(self) -> str:
        if not self.eval_rows:
            return "eval -"
        last = self.eval_rows[-1]
        return (f"eval {float(last[f'{self.reported}_mean']):.1f} @ "
                f"{int(float(last['Step'])):,}")

    def _record_evaluation(self, step: int, e: Mapping[str, Any]):
        """Writes the test returns of the evaluated actors at env step `step` (eval.csv: the
        reported actor's)."""
        if self.eval_rows and int(float(self.eval_rows[-1]["Step"])) == step:
            return  # already recorded (a finished run extended with a larger total_steps)
        actors, reported = self.agent.evaluated, self.reported
        self.eval_log.write([len(self.eval_rows), step, e[f"eval/{reported}_mean"],
                             e[f"eval/{reported}_std"], *e[schema.returns_key(reported)]])
        evaluated = schema.evaluation_metrics(actors)
        row = [step] + [e[m.key] for m in evaluated]
        self.policies_log.write(row)
        self.eval_rows.append(dict(zip(rundir.eval_policies_columns(actors), row)))
        self.tensorboard.scalars({m.key: e[m.key] for m in evaluated}, step)
        rundir.plot_learning_curve(self.dir / rundir.CURVE, self.eval_rows, actors,
                                   f"{self.run.algo.upper()} {self.run.env}, "
                                   f"seed {self.run.seed}")
        self.bar.set_postfix_str(f"gen {self.generation}, " + self._last_eval_text(),
                                 refresh=False)
        first, *others = actors
        tqdm.write(f"steps {step:>10,}  eval {_SHORT[first]} "
                   f"{float(e[f'eval/{first}_mean']):10.2f} ± {float(e[f'eval/{first}_std']):8.2f}"
                   + "".join(f"   {_SHORT[a]} {float(e[f'eval/{a}_mean']):10.2f}"
                             for a in others))

    # --- checkpoints ------------------------------------------------------------------
    def kept(self) -> str:
        """What a run that stops now leaves to resume from."""
        return (f"the last good checkpoint is generation {self.last_saved} in "
                f"{self.dir.checkpoints}" if self.last_saved is not None
                else "no checkpoint had been written yet")

    def save(self, state):
        """A checkpoint of the state with the logs' sizes; then the μ actor file."""
        for log in self.logs.values():
            log.sync()
        self.tensorboard.flush()
        meta = {"config": self.p.resolved, "generation": self.generation,
                "total_steps": self.total, "elapsed_s": self.elapsed(),
                "logs": {name: log.size() for name, log in self.logs.items()},
                "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        self.checkpoints.save(self.generation, state, meta)
        self.last_saved, self.checkpointed = self.generation, time.perf_counter()
        self.save_actors(state)

    def save_actors(self, state):
        """The evaluated actors of `state` as flat vectors in actors.npz."""
        actors = dict(zip(self.agent.evaluated,
                          jax.device_get(self.agent.evaluated_actors(state))))
        rundir.save_actors(self.dir / rundir.ACTORS, self.generation, self.total, **actors)

    def close(self):
        if self.bar is not None:
            self.bar.close()
        if self.tensorboard is not None:
            self.tensorboard.close()
        for log in self.logs.values():
            log.close()
        self.checkpoints.close()


def train(p: Plan) -> str:
    """Runs a Plan to the end of its budget or a stop request: returns "done" or the signal's
    name. Raises NonFiniteError (nothing checkpointed after the last good generation) or
    RunFailed when a file cannot be written (the last good checkpoint kept)."""
    from pgps_jax.cli import run_physics
    env = run_physics.env_for(p.run.env, p.run.physics)
    p.directory.write_config(p.resolved)
    trainer = Trainer(p, make_agent(p.run.algo, p.config, env, p.run.evaluation))
    failed = None
    try:
        return _run(trainer, p)
    except WriteFailed as e:
        failed = e
        raise _write_failure(e, trainer) from None
    finally:
        try:
            trainer.close()
        except WriteFailed as e:
            if failed is None:  # otherwise the write that failed first is the one reported
                raise _write_failure(e, trainer) from None


def _write_failure(error: WriteFailed, trainer: Trainer) -> RunFailed:
    return RunFailed(f"{error}; stopping. {trainer.kept().capitalize()}; once the file can be "
                     f"written, continue with resume=true.")


def _run(trainer: Trainer, p: Plan) -> str:
    """`train`'s loop, its final checkpoint and its summary line."""
    with StopRequest() as stop:
        state = trainer.start()
        while trainer.total < p.run.total_steps and stop.requested is None:
            state = trainer.step(state)
        if trainer.last_saved != trainer.generation:
            trainer.save(state)
    trainer.bar.close()
    if stop.requested is not None and trainer.total < p.run.total_steps:
        print(f"{stop.requested}: stopped at generation {trainer.generation} "
              f"({trainer.total:,} env steps); checkpoint written to "
              f"{trainer.dir.checkpoints}. Continue with resume=true "
              f"(or resume={trainer.dir.path}).", file=sys.stderr)
        return stop.requested
    last = trainer.eval_rows[-1] if trainer.eval_rows else None
    reported = trainer.reported
    summary = (f"final {_SHORT[reported]} return {float(last[f'{reported}_mean']):.2f} ± "
               f"{float(last[f'{reported}_std']):.2f}" if last else "no evaluation")
    print(f"done: {trainer.total:,} env steps in {trainer.generation} generations, "
          f"{trainer.elapsed():.0f} s of training; {summary}; outputs in {trainer.dir.path}")
    return "done"

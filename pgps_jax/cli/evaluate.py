"""`python -m pgps_jax.evaluate run=<dir>`: re-evaluate the actors a run saved (PGPS: μ, TD3,
elite; a baseline: the actors it evaluates).

    python -m pgps_jax.evaluate run=runs/halfcheetah/seed0
    python -m pgps_jax.evaluate run=runs/halfcheetah/seed0 episodes=50 seed=7 out=eval50.csv

Loads `<dir>/config.yaml` and `<dir>/actors.npz` (the evaluated actors of the run's last
checkpoint, i.e. the final ones once the run has finished) and plays deterministic test
episodes exactly as training does. With the defaults (the run's `eval_episodes`, start states
from PRNGKey(seed + 100)) the first line (the reported actor: μ, or TD3 alone's actor)
reproduces the run's last row of eval.csv.

Arguments (key=value): run (required); episodes (default: the run's eval_episodes);
steps (a test episode's step limit; default: the run's eval_steps); seed (the evaluation key
is PRNGKey(seed); default: the run's seed + 100); out (write the reported actor's result as a
CSV in the reference format: ,Step,Mean,Std,Reward1..).
"""

import dataclasses
import sys
from typing import TYPE_CHECKING, Mapping, Optional, Sequence

import numpy as np

from pgps_jax.agent.config import EvaluationConfig, PGPSConfig
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.errors import EXIT_OK, report
from pgps_jax.cli.tool_args import load_run, parse_args, require_writable

if TYPE_CHECKING:
    import jax


def evaluate_actors(algo: str, config: PGPSConfig, evaluation: EvaluationConfig, env,
                    actors: Mapping[str, np.ndarray], key: "jax.Array") -> dict[str, dict]:
    """{name: {"returns": [episodes], "mean", "std"}} of the actors that `algo` evaluates
    (`actors` keyed by their names), as its agent's `evaluate` plays them: deterministic
    episodes of `evaluation.steps` steps from the start states drawn from `key`."""
    import jax

    from pgps_jax.agent.algorithms import make_agent
    agent = make_agent(algo, config, env, evaluation)
    stacked = jax.numpy.stack([jax.numpy.asarray(actors[name]) for name in agent.evaluated])
    metrics = jax.device_get(jax.jit(agent.evaluate)(stacked, key))
    return {name: {"returns": metrics[f"eval/{name}_returns"],
                   "mean": float(metrics[f"eval/{name}_mean"]),
                   "std": float(metrics[f"eval/{name}_std"])}
            for name in agent.evaluated}


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return report(lambda: _evaluate(argv))


def _evaluate(argv: Sequence[str]) -> int:
    args = parse_args(argv, {"run": str, "episodes": int, "steps": int, "seed": int,
                             "out": str}, __doc__, required=("run",),
                      at_least={"episodes": 1, "steps": 1, "seed": 0})
    settings, config, saved = load_run(args["run"])
    out = require_writable(args["out"]) if "out" in args else None
    import jax  # only once the arguments are known to be good

    from pgps_jax.cli import run_physics
    env = run_physics.run_env(args["run"], settings.env, settings.physics)
    key_seed = args.get("seed", settings.seed + 100)
    evaluation = settings.evaluation
    evaluation = dataclasses.replace(evaluation, **{name: args[name] for name in
                                                    ("episodes", "steps") if name in args})
    results = evaluate_actors(settings.algo, config, evaluation, env, saved,
                              jax.random.PRNGKey(key_seed))
    print(f"{args['run']}: {settings.algo} on {settings.env}, generation {saved['generation']}, "
          f"{saved['env_steps']:,} env steps; {evaluation.episodes} episodes of "
          f"{evaluation.steps} steps, key PRNGKey({key_seed})")
    for name, r in results.items():
        print(f"  {name:6s} {r['mean']:12.4f} ± {r['std']:10.4f}   "
              + " ".join(f"{float(x):.2f}" for x in r["returns"]))
    if out is not None:
        reported = next(iter(results.values()))
        header = rundir.eval_columns(len(reported["returns"]))
        line = [0, saved["env_steps"], reported["mean"], reported["std"],
                *map(float, reported["returns"])]
        text = ",".join(header) + "\n" + ",".join(rundir.cell(c) for c in line) + "\n"
        rundir.write_atomic(out, text.encode())
        print(f"wrote {args['out']}")
    return EXIT_OK

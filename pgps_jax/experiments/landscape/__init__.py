"""The objective landscape of a linear tanh policy, one parameter at a time (Appendix A).

Appendix A of the paper (Figures 1 and 7) explains why gradient methods struggle on swimmer:
train a linear actor a = tanh(s·W), W ∈ R^{obs × act} and no bias, with the CEM until its
return exceeds 200; then move one entry of W over a range while the others stay fixed and
evaluate each point on 30 seeds, recording

    J(s_0)  ≈ 1/30 Σ_n Σ_{t=0}^{999} γ^t r_t   (average discounted return, γ = 0.99)
    Return  ≈ 1/30 Σ_n Σ_{t=0}^{999} r_t       (average undiscounted return).

The curves show wide flat regions (∇_θ J ≈ 0) and steep, step-like jumps.

Modules (pure functions; host-side I/O is kept in the functions marked "host"):
- `config`: the settings of the search (`TrainConfig`) and of the sweep (`SweepConfig`).
- `search`: `linear_policy` and `evaluate`, the actor and a batch of its episodes
  (`rollout.run_episodes`); `cem_generation` / `train_linear_policy`, the project's CEM on
  the flat W: one
  jitted generation, a host loop that stops at the threshold or gives up after
  `max_generations` and keeps the best parameters found.
- `sweep`: `sweep_parameter`, every point × seed of one parameter in ONE vmapped batch of episodes.
  The entry index is traced, so all parameters share one compiled function. Every point uses
  the same 30 reset keys (common random numbers), so differences between neighbouring points
  come from the parameter, not from the seeds.
  `analyse_curve`: flat fraction and largest jump of a curve (see its docstring).
- `output` (host): the sweeps' CSVs, `landscape.png` and the analysis table.
- `command` (host): `run` trains or loads, sweeps and writes (with `theta.npz`); `main` is the
  command line.

Command line (Hydra, config `configs/landscape.yaml`):

    python -m pgps_jax.landscape env=swimmer [threshold=200] [params_file=theta.npz]
        [sweep.params='[0,5,[3,1]]'] [sweep.points=41] [sweep.seeds=30] [steps=1000]
"""

from pgps_jax.experiments.landscape.command import main, run
from pgps_jax.experiments.landscape.config import SweepConfig, TrainConfig, resolve_params
from pgps_jax.experiments.landscape.output import ANALYSIS_COLUMNS, CSV_COLUMNS
from pgps_jax.experiments.landscape.search import (TrainResult, evaluate, linear_policy,
                                                   load_theta, save_theta,
                                                   train_linear_policy)
from pgps_jax.experiments.landscape.sweep import (Sweep, analyse_curve, make_sweep,
                                                  sweep_parameter, sweep_values)

__all__ = ["ANALYSIS_COLUMNS", "CSV_COLUMNS", "Sweep", "SweepConfig", "TrainConfig",
           "TrainResult", "analyse_curve", "evaluate", "linear_policy", "load_theta", "main",
           "make_sweep", "resolve_params", "run", "save_theta", "sweep_parameter",
           "sweep_values", "train_linear_policy"]

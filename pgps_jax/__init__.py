"""PGPS in JAX: `PGPS(config, env)` with pure `init`, `generation_step` and `evaluate` over a
`TrainState`; `for_task` gives the paper's configuration of a task and `make_env` the task.
The baselines built from the same parts share that interface: `make_agent(algo, config, env)`
with `for_task(task, algo)` (`CEMAlone`, `TD3Alone`, `CEMRL`). `couplings_of` switches PGPS's
couplings per state, to vmap Table 1's models in one program. `Checkpoints` saves and
restores a `TrainState` with orbax.

    from pgps_jax import PGPS, for_task, make_env

The package's layers: `pgps_jax.agent` (the algorithm), `pgps_jax.envs` (the tasks on MJX),
`pgps_jax.cli` (the commands and their runs), `pgps_jax.experiments`. Importing `pgps_jax`
loads none of them; each name below loads its module on first use.
"""

import importlib

_PUBLIC = {
    "PGPS": "pgps_jax.agent.pgps",
    "CEMAlone": "pgps_jax.agent.baselines.cem",
    "TD3Alone": "pgps_jax.agent.baselines.td3",
    "CEMRL": "pgps_jax.agent.baselines.cemrl",
    "make_agent": "pgps_jax.agent.algorithms",
    "TrainState": "pgps_jax.agent.base",
    "PGPSConfig": "pgps_jax.agent.config",
    "for_task": "pgps_jax.agent.config",
    "EvaluationConfig": "pgps_jax.agent.config",
    "couplings_of": "pgps_jax.agent.couplings",
    "make_env": "pgps_jax.envs",
    "Checkpoints": "pgps_jax.cli.checkpoint",
}
__all__ = list(_PUBLIC)


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'pgps_jax' has no attribute {name!r}")
    return getattr(importlib.import_module(_PUBLIC[name]), name)

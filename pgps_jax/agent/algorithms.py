"""PGPS and its baselines by name (`algo=<name>`): the agent classes and `make_agent`."""

import functools

from pgps_jax.agent.base import Agent, check_settings_types
from pgps_jax.agent.baselines.cem import CEMAlone
from pgps_jax.agent.baselines.cemrl import CEMRL
from pgps_jax.agent.baselines.td3 import TD3Alone
from pgps_jax.agent.config import ALGORITHMS, EvaluationConfig, PGPSConfig
from pgps_jax.agent.pgps import PGPS
from pgps_jax.envs import Env

AGENTS: dict[str, type[Agent]] = {cls.name: cls for cls in (PGPS, CEMAlone, TD3Alone, CEMRL)}


def make_agent(algo: str, config: PGPSConfig, env: Env,
               evaluation_config: EvaluationConfig = EvaluationConfig()) -> Agent:
    """The agent of algorithm `algo` (one of `ALGORITHMS`); ValueError naming the valid ones.
    Give it `for_task(task, algo)` for the algorithm's published hyper-parameters. Equal
    arguments give the same agent, whose programs the training loop compiles once per
    process (`pgps_jax.cli.loop`)."""
    if algo not in AGENTS:
        raise ValueError(f"unknown algorithm {algo!r}; valid: {', '.join(ALGORITHMS)}")
    check_settings_types(AGENTS[algo].__name__, config, evaluation_config)
    return _built(algo, config, env, evaluation_config)


@functools.lru_cache(maxsize=32)
def _built(algo: str, config: PGPSConfig, env: Env,
           evaluation_config: EvaluationConfig) -> Agent:
    return AGENTS[algo](config, env, evaluation_config)

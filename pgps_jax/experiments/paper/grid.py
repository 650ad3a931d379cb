"""The paper's experiments as grids of cells: (task, configuration), each run on several seeds.

A cell's configuration is the paper's for its task (`for_task`, Tables 3 and 4) with a few
fields replaced; its seeds run vmapped in one program (`pgps_jax.experiments.paper.runner`).

- `figure4`: PGPS and the baselines (CEM, TD3, CEM-RL; `pgps_jax.agent.algorithms`) on the
  five tasks (Figure 4 and the table of final returns); a configuration per algorithm.
- `table1`: the five cumulative models of Table 1 on halfcheetah, walker2d and ant: Base, then
  + PG→EA, + EA→PG, + Q-critic filtering, + increasing evaluation steps (= PGPS).
- `figure5`: swimmer, the TD3 actor with and without EA guidance (EA→PG).
- `figure6`: halfcheetah, PGPS; its per-generation returns of the Q-filtered and the randomly
  sampled actors are Figure 6.
"""

import dataclasses
from typing import Any, Mapping

from pgps_jax.agent.config import ALGORITHMS, TASK_NAMES


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (task, configuration) of an experiment."""

    task: str
    config: str
    """The configuration's name: a folder of the results."""
    overrides: Mapping[str, Any]
    """PGPSConfig fields replacing the algorithm's for this task."""
    algo: str = "pgps"
    """The algorithm (`ALGORITHMS`), with its configuration for the task (`for_task`)."""


_BASE = dict(pg_guides_ea=False, ea_guides_pg=False, q_filter=False, increasing_steps=False)
_CUMULATIVE = (
    ("base", _BASE),
    ("pg_to_ea", {**_BASE, "pg_guides_ea": True}),
    ("ea_to_pg", {**_BASE, "pg_guides_ea": True, "ea_guides_pg": True}),
    ("q_filter", {**_BASE, "pg_guides_ea": True, "ea_guides_pg": True, "q_filter": True}),
    ("pgps", {}),
)

EXPERIMENTS: dict[str, tuple[Cell, ...]] = {
    "figure4": tuple(Cell(task, algo, {}, algo) for task in TASK_NAMES for algo in ALGORITHMS),
    "table1": tuple(Cell(task, name, overrides)
                    for task in ("halfcheetah", "walker2d", "ant")
                    for name, overrides in _CUMULATIVE),
    "figure5": (Cell("swimmer", "pgps", {}),
                Cell("swimmer", "without_ea_guidance", {"ea_guides_pg": False})),
    "figure6": (Cell("halfcheetah", "pgps", {}),),
}


def cells(experiment: str, tasks: tuple[str, ...] = (), configs: tuple[str, ...] = ()
          ) -> tuple[Cell, ...]:
    """The cells of `experiment`, only those of `tasks` (in their order: the order the cells
    start in) and `configs` where given; ValueError naming the valid choices otherwise."""
    if experiment not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {experiment!r}; valid: {', '.join(EXPERIMENTS)}")
    grid = EXPERIMENTS[experiment]
    for kind, chosen, valid in (("task", tasks, {c.task for c in grid}),
                                ("configuration", configs, {c.config for c in grid})):
        unknown = sorted(set(chosen) - valid)
        if unknown:
            raise ValueError(f"{experiment} has no {kind} {', '.join(unknown)}; valid: "
                             f"{', '.join(sorted(valid))}")
    chosen = [c for c in grid if (not tasks or c.task in tasks)
              and (not configs or c.config in configs)]
    return tuple(sorted(chosen, key=lambda c: tasks.index(c.task)) if tasks else chosen)

"""The paper's experiments (Section 5): Figure 4 and its final returns, Table 1, Figures 5
and 6, as grids of (task, configuration) cells run on several seeds at once.

- `grid`: the experiments and their cells.
- `runner`: one cell, its seeds vmapped and sharded over the devices, resumable.
- `side_by_side`: several cells at a time, each in a process of its own.
- `command`: `python -m pgps_jax.experiments.paper <experiment>`.
"""

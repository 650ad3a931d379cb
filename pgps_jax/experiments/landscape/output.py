"""The experiment's files: the sweeps' CSVs, the figure and the analysis table (host)."""

import csv
import pathlib
from typing import Sequence

import numpy as np

from pgps_jax.experiments.landscape.sweep import Sweep


CSV_COLUMNS = ("value", "discounted_mean", "discounted_std", "return_mean", "return_std",
               "unstable_fraction")
"""Columns of each parameter's CSV; one row per swept value (means/stds over the seeds)."""

ANALYSIS_COLUMNS = ("parameter", "row", "col", "trained_value", "flat_fraction",
                    "max_jump_discounted", "max_jump_at", "max_jump_relative",
                    "max_jump_return", "discounted_range", "return_range")
"""Columns of `analysis.csv`, one row per panel (see `analyse_curve`)."""


def param_label(index: int, shape: tuple) -> str:
    """'W[row,col]' for a flat index into W [obs, act]."""
    row, col = divmod(index, shape[1])
    return f"W[{row},{col}]"


def write_sweep_csv(path: pathlib.Path, sweep: Sweep) -> None:
    """(host) One row per value with `CSV_COLUMNS` (mean and std over the seeds)."""
    disc, ret = np.asarray(sweep.discounted), np.asarray(sweep.returns)
    unstable = np.asarray(sweep.unstable, np.float64)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        for i, value in enumerate(np.asarray(sweep.values)):
            writer.writerow([f"{value:.6g}", f"{disc[i].mean():.6g}", f"{disc[i].std():.6g}",
                             f"{ret[i].mean():.6g}", f"{ret[i].std():.6g}",
                             f"{unstable[i].mean():.6g}"])


def plot_landscape(path: pathlib.Path, sweeps: Sequence[Sweep], labels: Sequence[str],
                   trained: Sequence[float], title: str) -> None:
    """(host) One panel per parameter: discounted (left axis) and undiscounted return (right
    axis) means, shaded ± std over the seeds, trained value dashed (like Figure 7)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = min(3, len(sweeps))
    nrows = -(-len(sweeps) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.2 * ncols, 3.0 * nrows), squeeze=False)
    for ax, sweep, label, center in zip(axes.flat, sweeps, labels, trained):
        x = np.asarray(sweep.values)
        twin = ax.twinx()
        for axis, data, color, name in ((ax, sweep.discounted, "tab:blue", "discounted J(s0)"),
                                        (twin, sweep.returns, "tab:red", "return")):
            data = np.asarray(data)
            mean, std = data.mean(axis=1), data.std(axis=1)
            axis.plot(x, mean, color=color, lw=1.4, label=name)
            axis.fill_between(x, mean - std, mean + std, color=color, alpha=0.2, lw=0)
            axis.tick_params(axis="y", labelcolor=color, labelsize=7)
        ax.axvline(center, color="grey", ls="--", lw=0.8)
        ax.set_title(label, fontsize=9)
        ax.tick_params(axis="x", labelsize=7)
        ax.set_ylabel("discounted J(s0)", color="tab:blue", fontsize=8)
        twin.set_ylabel("return", color="tab:red", fontsize=8)
    for ax in list(axes.flat)[len(sweeps):]:
        ax.set_visible(False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def format_analysis(rows: Sequence[dict]) -> str:
    """(host) The end-of-run table: one line per panel."""
    lines = [f"{'parameter':>10} {'trained':>8} {'flat frac':>9} {'max jump J':>10} "
             f"{'at':>8} {'jump/range':>10} {'max jump R':>10}"]
    for r in rows:
        lines.append(f"{r['parameter']:>10} {r['trained_value']:8.3f} {r['flat_fraction']:9.2f} "
                     f"{r['max_jump_discounted']:10.3f} {r['max_jump_at']:8.3f} "
                     f"{r['max_jump_relative']:10.2f} {r['max_jump_return']:10.2f}")
    return "\n".join(lines)

"""An experiment's report from its cells' results: the learning curves of the actor each
algorithm reports (μ; TD3 alone's actor) beside the authors' published ones, and the final
returns with their interquartile mean (IQM) and its 95 % stratified-bootstrap confidence
interval (Agarwal et al., 2021, "Deep reinforcement learning at the edge of the statistical
precipice": rliable's `StratifiedBootstrap`, percentile interval).

Writes into `<out>/<experiment>/`: `<task>.png` (the test return against env steps, mean ± std
over the seeds, of every configuration run on the task — and of any other folder there with a
`result.json`, the peers of `benchmarks.peers` — and the paper's PGPS; of the TD3 actor in
`figure5`, as the paper's Figure 5), `final_returns.md` (per task and run, labelled by
`run_label`: the env steps, the final return of each seed, mean ± std, IQM [95 % CI], and the
paper's); for `figure6` also `<task>_<config>_q_filter.png` (Figure 6: per 10k env steps, the
mean return of the Q-filtered actors and of the randomly sampled ones), and for `table1` also
`table1.md` (`table1_rows`). "std" is the sample std over seeds throughout.
"""

import csv
import dataclasses
import json
import pathlib
import textwrap
from typing import Optional

import jax
import numpy as np

from pgps_jax.agent.config import effective_fields, for_task, saved_fields_as_run
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.errors import UsageError
from pgps_jax.experiments.paper.grid import Cell, cells
from pgps_jax.envs import make_env
from pgps_jax.experiments.paper.runner import physics_of, seed_file

REFERENCE = pathlib.Path("benchmarks/reference/pgps_curves")
"""The authors' published curves: `<task>/<seed>.csv`."""
GRID_STEP = 10_000
"""Curves are compared at every multiple of this many env steps."""
BOOTSTRAP_SAMPLES = 2_000
BOOTSTRAP_SEED = 0
"""Every row's bootstrap draws from PRNGKey(BOOTSTRAP_SEED): the same returns, the same
interval."""
REPORT = "final_returns.md"
LEGEND_WIDTH = 60
"""Characters per line of a figure's legend entry."""
REPORTED_ACTOR = {"figure5": "td3"}
"""The actor whose curves and final returns an experiment reports, where it is not the one
each algorithm reports (μ; TD3 alone's actor)."""
ACTOR_NAMES = {None: "μ (TD3 alone: its actor)", "td3": "the TD3 actor"}


@dataclasses.dataclass(frozen=True)
class Curves:
    """The test returns of one actor over several seeds on one grid of env steps."""

    steps: np.ndarray
    """[G] multiples of GRID_STEP up to the last that every seed reached."""
    returns: np.ndarray
    """[seeds, G]"""


def read_curve(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    """(Step, Mean) columns of a curve in the authors' format."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return (np.array([float(r["Step"]) for r in rows]),
            np.array([float(r["Mean"]) for r in rows]))


def on_grid(curves: list[tuple[np.ndarray, np.ndarray]]) -> Curves:
    """The curves interpolated linearly at every multiple of GRID_STEP that each of them
    reached (its last evaluation counts for the next GRID_STEP steps)."""
    reach = min(steps[-1] for steps, _ in curves) + GRID_STEP
    grid = np.arange(GRID_STEP, reach, GRID_STEP)
    return Curves(grid, np.stack([np.interp(grid, s, r) for s, r in curves]))


def iqm(scores: np.ndarray, axis: int = -1) -> np.ndarray:
    """The interquartile mean: the mean of the scores left after cutting ⌊n/4⌋ from each end
    (scipy's `trim_mean(scores, 0.25)`, as rliable computes it)."""
    n = scores.shape[axis]
    cut = int(0.25 * n)
    return np.take(np.sort(scores, axis=axis), np.arange(cut, n - cut), axis=axis).mean(axis)


def stratified_bootstrap_ci(scores: list[np.ndarray], key: jax.Array,
                            samples: int = BOOTSTRAP_SAMPLES, level: float = 0.95
                            ) -> tuple[float, float]:
    """Percentile interval of the IQM of the pooled `scores` (one array of runs per task),
    each task's runs drawn with replacement within the task (stratified)."""
    keys = jax.random.split(key, len(scores))
    drawn = [np.asarray(s)[np.asarray(jax.random.randint(k, (samples, len(s)), 0, len(s)))]
             for s, k in zip(scores, keys)]
    values = iqm(np.concatenate(drawn, axis=1))
    tail = (1 - level) / 2 * 100
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


@dataclasses.dataclass(frozen=True)
class Finals:
    """Final returns of one (task, configuration) over its seeds, with their statistics."""

    source: str
    steps: tuple[int, int]
    """The fewest and the most env steps at which a seed's return was measured."""
    returns: np.ndarray

    def row(self, key: jax.Array) -> list[str]:
        r = self.returns
        low, high = stratified_bootstrap_ci([r], key)
        low_steps, high_steps = self.steps
        steps = f"{low_steps:,}" + (f"–{high_steps:,}" if high_steps != low_steps else "")
        return [self.source, steps, " ".join(f"{x:,.0f}" for x in r),
                f"{r.mean():,.0f} ± {sample_std(r):,.0f}",
                f"{iqm(r):,.0f} [{low:,.0f}, {high:,.0f}]"]


def sample_std(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """The std over seeds with Bessel's correction (0 for a single seed)."""
    return values.std(axis=axis, ddof=1) if values.shape[axis] > 1 else values.std(axis=axis)


def seeds_in(directory: pathlib.Path) -> list[int]:
    """The seeds whose reported actor's curve (`seed<k>.csv`) a cell's folder holds, in
    order."""
    return sorted(int(p.stem[4:]) for p in directory.glob("seed*.csv") if p.stem[4:].isdigit())


def _seed_files(directory: pathlib.Path, actor: Optional[str],
                of: Optional[list[int]] = None) -> list[pathlib.Path]:
    """The curves of `actor` (None: the reported actor) in a cell's folder, in the order of
    their seeds (those of `of` alone, where given)."""
    actor = actor or ""
    return [directory / seed_file(seed, actor) for seed in seeds_in(directory)
            if (of is None or seed in of) and (directory / seed_file(seed, actor)).exists()]


def run_label(config: str, result: Optional[dict], cell: Optional[Cell]) -> str:
    """`ours: <config>`, followed by what the run changed from its cell's configuration in the
    grid (`--set` fields, `--env` arguments) and from its task's physics of today, as
    `FIELD=VALUE`s in parentheses."""
    settings = (result or {}).get("settings")
    if cell is None or settings is None:
        return f"ours: {config}"
    grid_config = effective_fields(json.loads(json.dumps(dataclasses.asdict(
        for_task(cell.task, cell.algo, **dict(cell.overrides))))))
    changed = {name: value for name, value in saved_fields_as_run(settings["config"]).items()
               if name in grid_config and value != grid_config[name]}
    changed.update(settings.get("env", {}))
    physics = physics_of(settings, cell.task)
    if physics is not None:  # a cell run on the task's physics of an earlier version, say
        today = make_env(cell.task).settings()
        changed.update({name: value for name, value in physics.items()
                        if today.get(name) != value})
    shown = ", ".join(f"{name}={json.dumps(value) if not isinstance(value, str) else value}"
                      for name, value in changed.items())
    return f"ours: {config}" + (f" ({shown})" if shown else "")


def _ours(directory: pathlib.Path, actor: Optional[str] = None, cell: Optional[Cell] = None
          ) -> tuple[Optional[Curves], Optional[Finals], Optional[dict]]:
    """A cell's curves of `actor` (None: the actor its algorithm reports; those written so
    far, or once it is done those of its result's seeds) and, once it is done, its final
    returns (labelled by `run_label`) and its `result.json`."""
    path = directory / "result.json"
    result = json.loads(path.read_text()) if path.exists() else None
    # once done, not the curves of seeds it is being given under way
    read = [read_curve(p) for p in _seed_files(directory, actor, result and result["seeds"])]
    curves = on_grid(read) if read and all(len(s) for s, _ in read) else None
    if result is None:
        return curves, None, None
    reported = actor or next(iter(result["final"]))  # the algorithm's evaluated actors, in order
    steps = (min(result["env_steps"]), max(result["env_steps"]))
    return curves, Finals(run_label(result["config"], result, cell), steps,
                          np.array(result["final"][reported])), result


def _paper(reference: pathlib.Path, task: str) -> tuple[Optional[Curves], Optional[Finals]]:
    """The authors' curves of `task` and their last rows (the paper's final returns)."""
    files = sorted((reference / task).glob("*.csv"), key=lambda p: int(p.stem))
    if not files:
        return None, None
    read = [read_curve(p) for p in files]
    last = [int(s[-1]) for s, _ in read]
    return on_grid(read), Finals("paper: PGPS", (min(last), max(last)),
                                 np.array([r[-1] for _, r in read]))


def write_report(experiment: str, out: pathlib.Path, reference: pathlib.Path = REFERENCE
                 ) -> list[pathlib.Path]:
    """Writes the figures of every task of `experiment` that has results under `out`, and the
    table of final returns; returns the files written. UsageError if there are none."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root = out / experiment
    actor = REPORTED_ACTOR.get(experiment)
    tasks = list(dict.fromkeys(c.task for c in cells(experiment)))
    key = jax.random.PRNGKey(BOOTSTRAP_SEED)
    written, table, done = [], [], {}
    for task in tasks:
        grid = {c.config: c for c in cells(experiment, (task,))}
        configs = list(grid) + sorted(  # and the peers of benchmarks.peers
            d.name for d in (root / task).glob("*/")
            if d.name not in grid and (d / "result.json").exists())
        ours = {config: _ours(root / task / config, actor, grid.get(config))
                for config in configs if (root / task / config).is_dir()}
        if not ours:
            continue
        done.update({(task, config): result for config, (_, _, result) in ours.items()
                     if result is not None})
        paper = _paper(reference, task) if actor is None else (None, None)
        fig, ax = plt.subplots(figsize=(6, 4))
        for label, (curves, _) in [*((run_label(c, v[2], grid.get(c)), v[:2])
                                     for c, v in ours.items()), ("paper: PGPS", paper)]:
            if curves is None:
                continue
            mean, std = curves.returns.mean(0), sample_std(curves.returns)
            line, = ax.plot(curves.steps, mean, marker=_lone_point(curves.steps),
                            label=textwrap.fill(  # long --set lists wrap
                                f"{label} ({_seed_count(len(curves.returns))})", LEGEND_WIDTH))
            ax.fill_between(curves.steps, mean - std, mean + std, alpha=0.2,
                            color=line.get_color())
        ax.set(title=task, xlabel="env steps",
               ylabel=f"test return of {ACTOR_NAMES[actor]} (mean ± std)")
        ax.legend(loc="upper left", fontsize=8)
        fig.tight_layout()
        figure = root / f"{task}.png"
        fig.savefig(figure, dpi=120)
        plt.close(fig)
        written.append(figure)
        for finals in [v[1] for v in ours.values()] + [paper[1]]:
            if finals is not None:
                table.append([task, *finals.row(key)])
        if experiment == "figure6":
            written += [_draw_q_filter(root / task / config,
                                       root / f"{task}_{config}_q_filter.png", task, plt)
                        for config in ours]
    if not written:
        raise UsageError(f"no results of {experiment} under {out}")
    if experiment == "table1":
        written.append(_write_table(root / "table1.md", ["model", "normalised score",
                                    "normalised wall-clock", "tasks"], table1_rows(done)))
    return written + [_write_table(root / REPORT, ["task", "run", "env steps",
                                   "final return per seed", "mean ± std", "IQM [95 % CI]"],
                                   table)]


def _write_table(path: pathlib.Path, header: list[str], rows: list[list[str]]
                 ) -> pathlib.Path:
    """A Markdown table, written atomically; returns its path."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    rundir.write_atomic(path, ("\n".join(lines) + "\n").encode())
    return path


def filtered_and_sampled(path: pathlib.Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From a `seed<k>_generations.csv`, the generations in which the critic chose actors:
    (env steps, mean return of the Q-filtered slots [N/2, N) (the TD3 actor's slot N−1
    left out where it played), mean return of the sampled slots [1, N/2))."""
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if float(r["q_filter_active"])]
    n = sum(1 for column in (rows[0] if rows else {}) if column.startswith("return_"))
    steps, filtered, sampled = [], [], []
    for r in rows:
        returns = [float(r[f"return_{i}"]) for i in range(n)]
        chosen = returns[n // 2:n - 1] if float(r["td3_in_population"]) else returns[n // 2:]
        steps.append(float(r["env_steps"]))
        filtered.append(np.mean(chosen) if chosen else np.nan)
        sampled.append(np.mean(returns[1:n // 2]) if n // 2 > 1 else np.nan)
    return np.array(steps), np.array(filtered), np.array(sampled)


def binned_means(series: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Per seed (env steps, values), the mean value in each span [kG, (k+1)G) of G =
    GRID_STEP steps, averaged over the seeds, for the spans every seed finished; returns the
    spans' ends and the means (NaN values left out)."""
    last = min(int(steps[-1]) // GRID_STEP for steps, _ in series)  # the last, unfinished span
    spans = np.arange(last)
    per_seed = []
    for steps, values in series:
        span = steps.astype(np.int64) // GRID_STEP
        per_seed.append([np.nanmean(values[span == k]) if np.any(~np.isnan(values[span == k]))
                         else np.nan for k in spans])
    per_seed = np.array(per_seed).reshape(len(series), len(spans))
    seen = ~np.all(np.isnan(per_seed), axis=0)
    return (spans[seen] + 1) * GRID_STEP, np.nanmean(per_seed[:, seen], axis=0)


def _seed_count(count: int) -> str:
    return f"{count} seed" if count == 1 else f"{count} seeds"


def _lone_point(x: np.ndarray) -> Optional[str]:
    """A marker for a curve of one point, which a line alone does not show."""
    return "o" if len(x) == 1 else None


def _draw_q_filter(directory: pathlib.Path, figure: pathlib.Path, task: str, plt
                   ) -> pathlib.Path:
    """Figure 6: the mean return of the Q-filtered and of the sampled actors per GRID_STEP env
    steps, averaged over the seeds."""
    fig, ax = plt.subplots(figsize=(6, 4))
    per_seed = [filtered_and_sampled(p) for p in sorted(directory.glob("seed*_generations.csv"))]
    per_seed = [s for s in per_seed if len(s[0])]
    if per_seed:
        for column, label in ((1, "Q-filtered actors"), (2, "randomly sampled actors")):
            ends, means = binned_means([(data[0], data[column]) for data in per_seed])
            ax.plot(ends, means, marker=_lone_point(ends), label=label)
    ax.set(title=f"{task}: actors of the population", xlabel="env steps",
           ylabel=f"mean return per {GRID_STEP:,} steps")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(figure, dpi=120)
    plt.close(fig)
    return figure


def table1_rows(done: dict) -> list[list[str]]:
    """Table 1 of the paper from the done cells' results ({(task, model): result}): per model,
    the mean over tasks of its mean final return divided by the Base model's on the task (the
    Base model's final return of a run is the better of μ's and the TD3 actor's, as the paper
    selects it), both over the seeds the two cells share (a cell with more seeds, Figure 4's
    PGPS reused, say, is scored on the Base model's), and the same ratio of wall-clock; only
    tasks where the Base model is done. Wall-clocks are compared only where both cells ran the
    same seeds in the same programs (`_ran_alike`), the tasks compared named after the ratio
    where they are fewer; "–" where no task's cells ran alike."""
    def score(task, model):
        result, base_seeds = done[(task, model)], set(done[(task, "base")]["seeds"])
        shared = [i for i, seed in enumerate(result["seeds"]) if seed in base_seeds]
        mu, td3 = (np.asarray(result["final"][actor])[shared] for actor in ("mu", "td3"))
        return float(np.mean(np.maximum(mu, td3) if model == "base" else mu))

    rows = []
    for model in dict.fromkeys(model for _, model in done):
        tasks = [task for task, m in done if m == model and (task, "base") in done]
        if not tasks:
            continue
        ratio = np.mean([score(t, model) / score(t, "base") for t in tasks])
        timed = [t for t in tasks if _ran_alike(done[(t, model)], done[(t, "base")])]
        walls = [done[(t, model)]["wall_s"] / done[(t, "base")]["wall_s"] for t in timed]
        wall = f"{np.mean(walls):.3f}" if timed else "–"
        if timed and timed != tasks:
            wall += f" ({' '.join(timed)})"
        rows.append([model, f"{ratio:.2f}", wall, " ".join(tasks)])
    return rows


def _ran_alike(result: dict, other: dict) -> bool:
    """Whether two cells' wall-clocks measure the same work: the same seeds, vmapped in the
    same programs (a cell run in parts sums its parts' wall-clocks, and vmapped seeds cost
    less than their number times one). Not whether they ran on the same GPU or beside the
    same other work: their records say where they ran."""
    def programs(r):
        return [p["seeds"] for p in r.get("parts", [])] or [r["seeds"]]
    return programs(result) == programs(other)

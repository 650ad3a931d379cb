"""The run directory and its writers: CSV logs, TensorBoard, the learning curve, the actors.

A run directory holds

    config.yaml          the resolved configuration (Hydra's composed YAML, every field)
    metrics.csv          one row per generation (`metrics_columns`)
    eval.csv             the reference format: ,Step,Mean,Std,Reward1..RewardE (the episodes
                         of the actor the algorithm reports: μ; TD3 alone's actor)
    eval_policies.csv    Step and the mean/std return of each evaluated actor (PGPS: μ, the
                         TD3 actor and the elite)
    tb/                  TensorBoard event files (x axis: env steps)
    learning_curve.png   redrawn at each evaluation
    actors.npz           the evaluated actors of the last checkpoint;
                         at the end of a run, the final ones
    checkpoints/<gen>/   orbax checkpoints (see `pgps_jax.cli.checkpoint`)
    damaged_checkpoints/ checkpoints that failed verification on resume, set aside
    .lock                held by the process training here (its pid and host inside)

Everything here is host-side and runs outside jit. Files other than the append-only logs are
written to a temporary name and renamed, so a reader never sees half a file. A write that
fails (disk full, permission lost, I/O error) raises `WriteFailed` naming the file.
"""

import contextlib
import csv
import fcntl
import math
import os
import pathlib
import socket
import tempfile
import time
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import yaml

from pgps_jax.agent.metrics import Metric, evaluation_metrics
from pgps_jax.cli.errors import UsageError, WriteFailed

CONFIG = "config.yaml"
METRICS = "metrics.csv"
EVAL = "eval.csv"
EVAL_POLICIES = "eval_policies.csv"
TENSORBOARD = "tb"
CURVE = "learning_curve.png"
ACTORS = "actors.npz"
CHECKPOINTS = "checkpoints"
LOCK = ".lock"
METRICS_HOST = ("steps_per_s", "wall_time_s")
"""Host-measured columns (they differ between runs; everything else is deterministic)."""


def metrics_columns(generation: Sequence[Metric]) -> list[str]:
    """The header of metrics.csv: an algorithm's per-generation metrics (its
    `generation_metrics()`), then the host-measured ones."""
    return [m.column for m in generation] + list(METRICS_HOST)


def eval_columns(episodes: int) -> list[str]:
    """The header of eval.csv: an unnamed index column, Step, Mean, Std, Reward1..RewardE."""
    return ["", "Step", "Mean", "Std"] + [f"Reward{i + 1}" for i in range(episodes)]


def eval_policies_columns(actors: Sequence[str]) -> list[str]:
    """The header of eval_policies.csv: Step, then mean and std of each of `actors`."""
    return ["Step"] + [m.column for m in evaluation_metrics(tuple(actors))]


def cell(value: Any) -> str:
    """One CSV cell: ints and bools as integers, floats with full precision (repr)."""
    value = np.asarray(value).item() if isinstance(value, (np.ndarray, np.generic)) else value
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else
                                                         ("inf" if value > 0 else "-inf"))
    return str(value)


@contextlib.contextmanager
def writing(path: pathlib.Path):
    """Turns an OSError raised inside into WriteFailed naming `path`."""
    try:
        yield
    except OSError as e:
        raise WriteFailed(path, e) from None


def write_atomic(path: pathlib.Path, data: bytes) -> None:
    """Writes `data` to `path` through a temporary file in the same directory and a rename."""
    with writing(path):
        _write_atomic(path, data)


def write_csv(path: pathlib.Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """A whole CSV file (cells as `cell` writes them), atomically."""
    lines = [",".join(header)] + [",".join(cell(v) for v in row) for row in rows]
    write_atomic(path, ("\n".join(lines) + "\n").encode())


def _write_atomic(path: pathlib.Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


class CsvLog:
    """An append-only CSV file: a header, then whole lines flushed to disk on `sync`."""

    def __init__(self, path: pathlib.Path, header: Sequence[str]):
        self.path, self.header = path, list(header)
        self._file = None

    def start(self) -> None:
        """A new file holding only the header."""
        with writing(self.path):
            self._file = open(self.path, "w", newline="")
            self._file.write(",".join(self.header) + "\n")
        self.sync()

    def reopen(self, size: int) -> None:
        """Continue the file after cutting it to `size` bytes (its size at a checkpoint)."""
        if not self.path.exists():
            raise UsageError(f"cannot resume: {self.path} is missing")
        actual = self.path.stat().st_size
        if actual < size:
            raise UsageError(f"cannot resume: {self.path} has {actual} bytes, fewer than the "
                             f"{size} it had at the checkpoint")
        with writing(self.path):
            with open(self.path, "r+b") as f:
                f.truncate(size)
        with open(self.path, newline="") as f:
            header = next(csv.reader(f), None)
        if header != self.header:
            raise UsageError(f"cannot resume: {self.path} has the columns {header}, "
                             f"expected {self.header}")
        with writing(self.path):
            self._file = open(self.path, "a", newline="")

    def write(self, cells: Sequence[Any]) -> None:
        with writing(self.path):
            self._file.write(",".join(cell(c) for c in cells) + "\n")

    def sync(self) -> None:
        """Flush to the OS and to disk (before a checkpoint records the size)."""
        with writing(self.path):
            self._file.flush()
            os.fsync(self._file.fileno())

    def size(self) -> int:
        with writing(self.path):
            self._file.flush()
        return self.path.stat().st_size

    def rows(self) -> list[dict]:
        """The data rows written so far."""
        with writing(self.path):
            self._file.flush()
        with open(self.path, newline="") as f:
            return list(csv.DictReader(f))

    def close(self) -> None:
        if self._file is not None:
            file, self._file = self._file, None
            with writing(self.path):
                file.close()


class RunLock:
    """An exclusive lock on a directory (flock on its file `path`: a run's `.lock`, a paper
    cell's seed locks), held until `release` or the process's end, SIGKILL included; `busy` is
    what a refusal advises."""

    def __init__(self, path: pathlib.Path,
                 busy: str = "wait for it to finish or stop it, or choose another run_dir"):
        self.path = path
        while True:
            with writing(path):
                file = open(path, "a+")
            try:
                fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                file.seek(0)
                holder = file.read().strip() or "another process"
                file.close()
                raise UsageError(f"{path.parent} is in use by {holder}; {busy}") from None
            except BaseException:
                file.close()
                raise
            if _is_file_at(file, path):
                break
            file.close()  # its holder removed it as this process locked it: lock the new one
        self._file = file
        try:
            with writing(path):
                file.seek(0)
                file.truncate()
                file.write(f"process {os.getpid()} on {socket.gethostname()}, started "
                           f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n")
                file.flush()
        except BaseException:  # Ctrl-C, say: no lock left behind
            self.release(remove=True)
            raise

    def release(self, remove: bool = False) -> None:
        """Unlocks; with `remove`, deletes the lock file first, while still holding it (a
        process that locked it meanwhile finds it gone, and locks the one then at `path`)."""
        if not self._file.closed:
            if remove:
                self.path.unlink(missing_ok=True)
            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()


def _is_file_at(file, path: pathlib.Path) -> bool:
    """Whether the open `file` is the one now at `path`."""
    try:
        at_path = os.stat(path)
    except FileNotFoundError:
        return False
    opened = os.fstat(file.fileno())
    return (opened.st_dev, opened.st_ino) == (at_path.st_dev, at_path.st_ino)


class RunDir:
    """Paths of one run directory and the checks done before training starts."""

    def __init__(self, path: str | os.PathLike):
        self.path = pathlib.Path(path).expanduser().absolute()

    def __truediv__(self, name: str) -> pathlib.Path:
        return self.path / name

    @property
    def checkpoints(self) -> pathlib.Path:
        return self.path / CHECKPOINTS

    def ensure_writable(self) -> None:
        """Creates the directory and writes a probe file, or raises a UsageError saying why."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            probe = self.path / ".write_test"
            probe.write_bytes(b"ok")
            probe.unlink()
        except OSError as e:
            raise UsageError(f"cannot write the run directory {self.path}: "
                             f"{e.strerror or e}") from None

    def lock(self) -> RunLock:
        """Locks the directory for this process; UsageError naming the holder if it is taken."""
        return RunLock(self.path / LOCK)

    def has_checkpoint(self) -> bool:
        """Whether a complete checkpoint exists (orbax's temporary directories do not count)."""
        directory = self.checkpoints
        return directory.is_dir() and any(p.name.isdigit() for p in directory.iterdir())

    def holds_run(self) -> bool:
        """Whether a run has already written here (checkpoints or logs)."""
        return self.has_checkpoint() or (self.path / METRICS).exists()

    def write_config(self, resolved: Mapping[str, Any]) -> None:
        """The resolved configuration as YAML (atomically)."""
        first = [k for k in ("env", "seed", "total_steps") if k in resolved]
        ordered = {k: resolved[k] for k in first + [k for k in resolved if k not in first]
                   if k != "pgps"}
        ordered["pgps"] = resolved.get("pgps")
        text = yaml.safe_dump(ordered, sort_keys=False, default_flow_style=None)
        write_atomic(self.path / CONFIG, text.encode())

    def read_config(self) -> dict:
        """The resolved configuration saved by the run."""
        path = self.path / CONFIG
        if not path.exists():
            raise UsageError(f"{self.path} is not a run directory: it has no {CONFIG}")
        try:
            with open(path) as f:
                config = yaml.safe_load(f)
        except yaml.YAMLError as e:
            raise UsageError(f"{path} cannot be read: it is not valid YAML ({e})") from None
        if not isinstance(config, dict):
            raise UsageError(f"{path} cannot be read: it holds no settings")
        return config


def save_actors(path: pathlib.Path, generation: int, env_steps: int,
                **flat_actors: np.ndarray) -> None:
    """The actors as flat parameter vectors (keyed by name: `mu`, `td3`, `elite`) in an
    .npz, atomically.

    Turn a vector into the flax parameter tree with `networks.actor_flattener`.
    """
    write_npz(path, generation=np.int64(generation), env_steps=np.int64(env_steps),
              **{k: np.asarray(v, np.float32) for k, v in flat_actors.items()})


def write_npz(path: pathlib.Path, **arrays: np.ndarray) -> None:
    """`arrays` in an .npz at `path`, written atomically (`write_atomic`)."""
    import io
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_atomic(path, buffer.getvalue())


def load_actors(path: pathlib.Path) -> dict:
    """{actor name: [P] for each saved actor, "generation": int, "env_steps": int}."""
    if not path.exists():
        raise UsageError(f"no saved actor {path}: the run has not written a checkpoint yet")
    with np.load(path) as data:
        out = {k: data[k] for k in data.files}
    out["generation"], out["env_steps"] = int(out["generation"]), int(out["env_steps"])
    return out


ACTOR_LABELS = {"mu": "μ (CEM mean)", "td3": "TD3 actor", "elite": "elite"}


def plot_learning_curve(path: pathlib.Path, rows: Sequence[Mapping[str, Any]],
                        actors: Sequence[str], title: str) -> None:
    """Draws eval_policies rows (Step, <actor>_mean, <actor>_std) to a PNG: the first of
    `actors` (the reported one) with its std band, the others as lines."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([float(r["Step"]) for r in rows])
    column = lambda name: np.array([float(r[name]) for r in rows])
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=100)
    reported, *others = actors
    mean, std = column(f"{reported}_mean"), column(f"{reported}_std")
    ax.plot(steps, mean, color="C0", marker="o", markersize=3, label=ACTOR_LABELS[reported])
    ax.fill_between(steps, mean - std, mean + std, color="C0", alpha=0.2)
    for i, actor in enumerate(others, start=1):
        ax.plot(steps, column(f"{actor}_mean"), color=f"C{i}", linewidth=1,
                label=ACTOR_LABELS[actor])
    ax.set_xlabel("env steps")
    ax.set_ylabel("return (deterministic test episodes)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    fig.tight_layout()
    import io
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    write_atomic(path, buffer.getvalue())


class TensorBoard:
    """Scalars to `<run>/tb`; on resume, events newer than the checkpoint are purged."""

    def __init__(self, directory: pathlib.Path, purge_step: Optional[int] = None):
        from tensorboardX import SummaryWriter
        self.directory = directory
        with writing(directory):
            self._writer = SummaryWriter(str(directory), purge_step=purge_step)

    def scalars(self, values: Mapping[str, Any], step: int) -> None:
        with writing(self.directory):
            for tag, value in values.items():
                self._writer.add_scalar(tag, float(np.asarray(value)), global_step=step)

    def flush(self) -> None:
        with writing(self.directory):
            self._writer.flush()

    def close(self) -> None:
        with writing(self.directory):
            self._writer.close()

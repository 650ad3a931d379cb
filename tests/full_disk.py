"""A disk that fills up: `fill(where, n, patch)` makes the n-th write (from 1) of a kind fail
with ENOSPC, `patch(owner, name, value)` replacing what it needs (pytest's
`monkeypatch.setattr`, undone after the test).
"""

import errno
import os

from etils import epath


def _fail_on(n: int):
    """A predicate that is true on its n-th call."""
    calls = [0]

    def due() -> bool:
        calls[0] += 1
        return calls[0] == n
    return due


def _full(path) -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def fill_checkpoints(n: int, patch) -> None:
    due = _fail_on(n)
    write_text = epath.gpath.PosixGPath.write_text

    def failing_write_text(self, *args, **kwargs):
        if "orbax-checkpoint-tmp" in str(self) and self.name == "metadata" and due():
            raise _full(self)
        return write_text(self, *args, **kwargs)
    patch(epath.gpath.PosixGPath, "write_text", failing_write_text)


class _FillingFile:
    """A text file whose writes fail with ENOSPC when `due()` says so."""

    def __init__(self, file, due):
        self._file, self._due = file, due

    def write(self, text: str) -> int:
        if self._due():
            raise _full(self._file.name)
        return self._file.write(text)

    def __getattr__(self, name):
        return getattr(self._file, name)


def fill_logs(n: int, patch) -> None:
    from pgps_jax.cli import run_dir as rundir
    due = _fail_on(n)

    def filling(open_log):
        def opened(self, *args):
            open_log(self, *args)
            if self.path.name == rundir.METRICS:
                self._file = _FillingFile(self._file, due)
        return opened
    patch(rundir.CsvLog, "start", filling(rundir.CsvLog.start))
    patch(rundir.CsvLog, "reopen", filling(rundir.CsvLog.reopen))


def fill(where: str, n: int, patch) -> None:
    """where = checkpoint: orbax's write of a checkpoint's JSON metadata, inside its temporary
    directory (the state's arrays are already written there); log: a data line of
    metrics.csv (counted from the first write after this call)."""
    {"checkpoint": fill_checkpoints, "log": fill_logs}[where](n, patch)

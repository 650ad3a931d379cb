"""`python tests/write_faults.py <where> <n> <train arguments...>`: `python -m pgps_jax.train`
with a disk that fills up: the n-th write (from 1) of a kind fails with ENOSPC.

where = checkpoint: orbax's write of a checkpoint's JSON metadata, inside its temporary
        directory (the state's arrays are already written there);
        log: a data line of metrics.csv (counted from the start of this process).
"""

import errno
import os
import sys

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


def fill_checkpoints(n: int) -> None:
    due = _fail_on(n)
    write_text = epath.gpath.PosixGPath.write_text

    def failing_write_text(self, *args, **kwargs):
        if "orbax-checkpoint-tmp" in str(self) and self.name == "metadata" and due():
            raise _full(self)
        return write_text(self, *args, **kwargs)
    epath.gpath.PosixGPath.write_text = failing_write_text


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


def fill_logs(n: int) -> None:
    from pgps_jax.cli import run_dir as rundir
    due = _fail_on(n)

    def filling(open_log):
        def opened(self, *args):
            open_log(self, *args)
            if self.path.name == rundir.METRICS:
                self._file = _FillingFile(self._file, due)
        return opened
    rundir.CsvLog.start = filling(rundir.CsvLog.start)
    rundir.CsvLog.reopen = filling(rundir.CsvLog.reopen)


if __name__ == "__main__":
    where, n, args = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
    {"checkpoint": fill_checkpoints, "log": fill_logs}[where](n)
    from pgps_jax.cli import train
    sys.argv = ["pgps_jax.train", *args]
    train.main()

"""The errors a command reports in one line, and its exit statuses.

Every command (`train`, `evaluate`, `render`, `landscape`) runs its body through `report`,
so a mistake in its input is one `error: ...` line on stderr and exit status 2, and a run
that fails on its way (a non-finite metric, a file that cannot be written, a device out of
memory) is one line and exit status 1: never a traceback.
"""

import errno
import os
import re
import sys
from typing import Callable

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class UsageError(Exception):
    """A bad setting or command line; the message says which and what is valid."""


class RunFailed(Exception):
    """A run stopped on its way; the message says why and what was kept."""


class WriteFailed(RunFailed):
    """A file of the run could not be written (disk full, permission lost, I/O error)."""

    def __init__(self, path, error: BaseException):
        self.path, self.cause = path, describe_os_error(error)
        super().__init__(f"cannot write {path}: {self.cause}")


_OS_ERROR_CODE = re.compile(r"os_error_code='?(\d+)")


def describe_os_error(error: BaseException) -> str:
    """The cause of a failed write in words: the OSError's text (searched for in the exception's
    chain, and in the error codes that tensorstore puts in orbax's messages), else its first
    line."""
    seen = error
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno is not None:
            return f"{os.strerror(seen.errno)} ({errno.errorcode.get(seen.errno, seen.errno)})"
        match = _OS_ERROR_CODE.search(str(seen))
        if match:
            code = int(match.group(1))
            return f"{os.strerror(code)} ({errno.errorcode.get(code, code)})"
        seen = seen.__cause__ or seen.__context__
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


def print_error(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)


def report(body: Callable[[], int]) -> int:
    """`body()`'s exit status; a UsageError is reported as status 2, a RunFailed as 1."""
    try:
        return body()
    except UsageError as e:
        print_error(str(e))
        return EXIT_USAGE
    except RunFailed as e:
        print_error(str(e))
        return EXIT_FAILED
    except Exception as e:
        if not is_out_of_memory(e):
            raise
        print_error(f"the device ran out of memory ({first_line(e)}). The settings that "
                    "size the programs' memory: pgps.buffer_size, pgps.batch_size, "
                    "pgps.ss1_size, pgps.ss2_size, pgps.pop_size × pgps.sample_ratio (the "
                    "candidates Q-filtering scores), the networks' widths and the seeds run "
                    "at once; a run keeps its last checkpoint")
        return EXIT_FAILED


def is_out_of_memory(error: BaseException) -> bool:
    """Whether `error` is XLA's report of an allocation the device could not make."""
    return (type(error).__name__ in ("JaxRuntimeError", "XlaRuntimeError")
            and "RESOURCE_EXHAUSTED" in str(error))


def first_line(error: BaseException) -> str:
    """An error's first line (at most 300 characters), or its type's name if it has none."""
    lines = str(error).strip().splitlines()
    return lines[0][:300] if lines else type(error).__name__

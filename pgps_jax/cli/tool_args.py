"""The `key=value` arguments of the tool commands (`evaluate`, `render`) and the saved run they
name. Imports neither JAX nor MuJoCo, so a command checks its input before loading either."""

import pathlib
import sys
import tempfile
from typing import Callable, Mapping, Sequence

from pgps_jax.cli import run_dir as rundir
from pgps_jax.agent.config import PGPSConfig
from pgps_jax.cli.errors import EXIT_OK, UsageError, describe_os_error
from pgps_jax.cli.run_config import RunSettings, from_dict


def parse_args(argv: Sequence[str], types: Mapping[str, Callable], usage: str,
               required: Sequence[str] = (), at_least: Mapping[str, int] = {}) -> dict:
    """`key=value` arguments -> {key: types[key](value)}; UsageError naming a bad one, or one
    below its bound in `at_least`. `-h` or `--help` prints `usage` (the command's docstring)
    and exits."""
    if "-h" in argv or "--help" in argv:
        print((usage or "").strip())  # no docstrings under python -OO
        sys.exit(EXIT_OK)
    values = {}
    for arg in argv:
        key, sep, text = arg.partition("=")
        if not sep or key not in types:
            raise UsageError(f"unknown argument {arg!r}; valid: "
                             + " ".join(f"{k}=..." for k in types))
        try:
            values[key] = types[key](text)
        except ValueError:
            raise UsageError(f"{key}={text!r} is invalid: expected {types[key].__name__}") from None
    for key in required:
        if key not in values:
            raise UsageError(f"missing argument {key}=...; valid: "
                             + " ".join(f"{k}=..." for k in types))
    for key, low in at_least.items():
        if key in values and values[key] < low:
            raise UsageError(f"{key}={values[key]} is invalid: must be an integer >= {low}")
    return values


def load_run(path: str) -> tuple[RunSettings, PGPSConfig, dict]:
    """(settings, config, saved actors) of the run directory `path`."""
    directory = rundir.RunDir(path)
    if not directory.path.is_dir():
        raise UsageError(f"run={path}: no such run directory")
    settings, config = from_dict(directory.read_config())
    return settings, config, rundir.load_actors(directory / rundir.ACTORS)


def require_writable(out: str) -> pathlib.Path:
    """`out` as an absolute path, once a file can be written beside it (before any work
    whose result it would hold); UsageError naming the cause otherwise."""
    path = pathlib.Path(out).absolute()
    if not out or path.is_dir():
        raise UsageError(f"out={out}: name a file to write, not a folder")
    try:
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}."):
            pass
    except OSError as e:
        raise UsageError(f"out={out}: cannot write there: {describe_os_error(e)}") from None
    return path

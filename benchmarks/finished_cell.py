"""Finished PGPS cells of the experiment runner, for the benchmarks that read a cell's
per-generation metrics (`mu_swings`, `guidance`): a cell's `result.json`, and the command's
measuring of every cell it is given."""

import argparse
import json
import pathlib
from typing import Callable

from pgps_jax.cli.run_dir import write_atomic


def pgps_result(cell: pathlib.Path, switch: str, without: str) -> dict:
    """The cell's `result.json`; ValueError naming the folder where it holds none (not a
    finished cell), where another algorithm ran it, and where the PGPSConfig switch `switch`
    was off (`without` says what that leaves to measure)."""
    path = cell / "result.json"
    if not path.exists():
        raise ValueError(f"{cell} holds no result.json: not a finished cell's folder")
    result = json.loads(path.read_text())
    if result["algo"] != "pgps":
        raise ValueError(f"{cell}: a cell of {result['algo']}; only PGPS's cells are read")
    if not result["settings"]["config"][switch]:
        raise ValueError(f"{cell}: {switch} is off, so {without}")
    return result


def measure_cells(parser: argparse.ArgumentParser, cells: list[pathlib.Path],
                  measure: Callable[[pathlib.Path], dict], table: Callable[[dict], str],
                  out: pathlib.Path) -> dict:
    """`measure` of each cell, keyed by its folder, written to `out` as JSON and printed as
    `table`; a cell `measure` refuses (ValueError) stops the command through `parser`, with
    nothing written."""
    try:
        results = {str(cell): measure(cell) for cell in cells}
    except ValueError as error:
        parser.error(str(error))
    write_atomic(out, (json.dumps(results, indent=1) + "\n").encode())
    print(table(results))
    print(f"wrote {out}")
    return results

"""The `result.json` of a finished PGPS cell of the experiment runner, for the benchmarks that
read a cell's per-generation metrics (`mu_swings`, `guidance`)."""

import json
import pathlib


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

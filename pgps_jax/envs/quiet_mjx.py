"""`mujoco.mjx`, imported without the lines it prints when its optional Warp backend is absent.

`mujoco.mjx` prints "Failed to import warp: No module named 'warp'" (and the same for
`mujoco_warp`) on import wherever Warp is not installed; MJX's JAX backend, the tasks'
default, does not need it. Any other line printed during the import still reaches stdout.
"""

import contextlib
import importlib
import io

_WARP_ABSENT = ("Failed to import warp:", "Failed to import mujoco_warp:")

with contextlib.redirect_stdout(io.StringIO()) as _printed:
    importlib.import_module("mujoco.mjx")

for _line in _printed.getvalue().splitlines():
    if not _line.startswith(_WARP_ABSENT):
        print(_line)

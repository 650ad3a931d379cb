"""`python -m pgps_jax.render` on a hopper run (real MJX physics, MuJoCo's offscreen renderer).

Rendering needs an offscreen OpenGL; where MuJoCo cannot open one, the tests that render are
skipped with the reason, and the error the command gives instead is checked."""

import os
import re
import subprocess
import sys
from typing import Optional

import imageio.v3 as iio
import numpy as np
import pytest

from conftest import HOPPER_RUN
from train_cli import run, run_here

pytestmark = HOPPER_RUN

STEPS = 12


def gl_unavailable(backend: str) -> Optional[str]:
    """None if MuJoCo opens an offscreen OpenGL context with MUJOCO_GL=`backend`, else why
    not (the probe's last line of error)."""
    probe = subprocess.run(
        [sys.executable, "-c", "import mujoco; mujoco.GLContext(8, 8).make_current()"],
        env={**os.environ, "MUJOCO_GL": backend}, capture_output=True, text=True, timeout=120)
    if probe.returncode == 0:
        return None
    return (probe.stderr.strip().splitlines() or [f"exit status {probe.returncode}"])[-1]


BACKEND = os.environ.get("MUJOCO_GL", "egl")
NO_GL = gl_unavailable(BACKEND)
needs_gl = pytest.mark.skipif(NO_GL is not None,
                              reason=f"no offscreen OpenGL (MUJOCO_GL={BACKEND}): {NO_GL}")


def _expected_frames(stdout: str) -> int:
    """The start state and every step played (all of them at max_fps=1000)."""
    steps = int(re.search(r", (\d+) steps", stdout).group(1))
    assert steps == STEPS or "(terminated)" in stdout
    return steps + 1


@needs_gl
def test_render_writes_a_gif_of_one_episode(task_runs, cache, tmp_path):
    run_dir, _ = task_runs("hopper")
    out = tmp_path / "episode.gif"
    result = run("render", [f"run={run_dir}", f"out={out}", f"steps={STEPS}", "width=96",
                            "height=64", "max_fps=1000"], cache, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    frames = iio.imread(out, index=None)
    assert frames.shape == (_expected_frames(result.stdout), 64, 96, 3)
    assert frames.std() > 0 and np.abs(frames[-1].astype(int) - frames[0]).sum() > 0
    assert "hopper" in result.stdout and f"{len(frames)} frames" in result.stdout


def test_render_mp4_needs_imageio_ffmpeg(task_runs, cache, tmp_path):
    """Without imageio-ffmpeg (hidden from the command's Python by a `sitecustomize`), an .mp4
    is refused with what to install, and nothing is written."""
    run_dir, _ = task_runs("hopper")
    out = tmp_path / "episode.mp4"
    hider = tmp_path / "without_ffmpeg"
    hider.mkdir()
    (hider / "sitecustomize.py").write_text("import sys\nsys.modules['imageio_ffmpeg'] = None\n")
    path = os.pathsep.join([str(hider), *filter(None, [os.environ.get("PYTHONPATH")])])
    result = run("render", [f"run={run_dir}", f"out={out}"], cache, tmp_path, PYTHONPATH=path)
    assert result.returncode == 2 and "pip install imageio-ffmpeg" in result.stderr
    assert not out.exists()


@needs_gl
def test_render_writes_an_mp4(task_runs, cache, tmp_path):
    run_dir, _ = task_runs("hopper")
    out = tmp_path / "episode.mp4"
    result = run("render", [f"run={run_dir}", f"out={out}", f"steps={STEPS}", "width=96",
                            "height=64", "max_fps=1000"], cache, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert len(iio.imread(out, index=None)) == _expected_frames(result.stdout)


def test_render_without_opengl_names_what_to_install(task_runs, cache, tmp_path):
    """OSMesa where it is missing (MuJoCo loads, its renderer fails), else a backend MuJoCo
    does not know (MuJoCo fails to load): either way the command says what to install."""
    backend = "osmesa" if gl_unavailable("osmesa") is not None else "no-such-backend"
    run_dir, _ = task_runs("hopper")
    out = tmp_path / "episode.gif"
    result = run("render", [f"run={run_dir}", f"out={out}", "steps=2"], cache, tmp_path,
                 MUJOCO_GL=backend)
    assert result.returncode == 2, result.stderr[-3000:]
    assert "apt-get install libegl1" in result.stderr and "libosmesa6" in result.stderr
    assert "Traceback" not in result.stderr and not out.exists()


@pytest.mark.parametrize("args, words", [
    ([], ["missing argument run="]),
    (["run=/nonexistent/run"], ["no such run directory"]),
    (["policy=best"], ["policy='best'", "mu, td3, elite"]),
    (["out=episode.avi"], [".mp4 or .gif"]),
    (["colour=red"], ["unknown argument 'colour=red'"]),
    (["steps=0"], ["steps=0 is invalid: must be an integer >= 1"]),
    (["out=missing/episode.gif"], ["out=missing/episode.gif: cannot write there",
                                   "No such file"]),
])
def test_render_bad_arguments(task_runs, tmp_path, args, words):
    run_dir, _ = task_runs("hopper")
    base = [] if args in ([], ["run=/nonexistent/run"]) else [f"run={run_dir}"]
    result = run_here("render", base + args, tmp_path)
    assert result.returncode == 2
    for word in words:
        assert word in result.stderr
    assert "Traceback" not in result.stderr


def test_importing_the_command_leaves_the_gl_backend_alone():
    """Only the command picks MUJOCO_GL (before MuJoCo's first import): importing its module
    into a process (a test worker, a user's script) must not choose a backend for the
    process's later `import mujoco` or for its child processes."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY")}
    probe = subprocess.run(
        [sys.executable, "-c", "import os, pgps_jax.cli.render; "
                               "print(os.environ.get('MUJOCO_GL'))"],
        env=env, capture_output=True, text=True, timeout=120)
    assert probe.returncode == 0, probe.stderr[-2000:]
    assert probe.stdout.strip() == "None"

"""`python -m pgps_jax.render` and `python -m pgps_jax.evaluate` on a MuJoCo task's run directory.

The run directory is made by hand (a resolved halfcheetah configuration with a small actor and
a saved actor file), so no training is needed.
"""

import importlib.util

import imageio.v3 as iio
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pgps_jax import run_dir as rundir
from pgps_jax.run_config import CONFIG_DIR, register_structured_configs

from train_cli import run

register_structured_configs()
OBS, ACT, HIDDEN = 17, 6, 8


@pytest.fixture(scope="module")
def halfcheetah_run(tmp_path_factory):
    directory = rundir.RunDir(tmp_path_factory.mktemp("hc") / "run")
    directory.ensure_writable()
    overrides = ["env=halfcheetah", f"pgps.actor_hidden=[{HIDDEN}]", "pgps.eval_steps=20",
                 "pgps.eval_episodes=2"]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        values = OmegaConf.to_container(compose("config", overrides=overrides), resolve=True)
    directory.write_config(values)
    rng = np.random.default_rng(0)
    size = OBS * HIDDEN + HIDDEN + HIDDEN * ACT + ACT
    actors = {name: rng.normal(0, 0.5, size).astype(np.float32) for name in ("mu", "td3", "elite")}
    rundir.save_actors(directory / rundir.ACTOR, 7, 12345, **actors)
    return directory.path


def test_render_writes_a_gif_of_one_episode(halfcheetah_run, tmp_path):
    out = tmp_path / "episode.gif"
    result = run("render", [f"run={halfcheetah_run}", f"out={out}", "steps=12", "width=96",
                            "height=64"], tmp_path / "cache", tmp_path)
    if result.returncode != 0:  # no offscreen OpenGL here: the error must say what to install
        assert result.returncode == 2 and "apt-get install libegl1" in result.stderr
        assert "libosmesa6" in result.stderr and not out.exists()
        return
    frames = iio.imread(out, index=None)
    assert frames.shape == (13, 64, 96, 3)  # the start state and 12 steps
    assert frames.std() > 0 and np.abs(frames[-1].astype(int) - frames[0]).sum() > 0
    assert "halfcheetah" in result.stdout and "13 frames" in result.stdout


def test_render_mp4_needs_imageio_ffmpeg_or_works(halfcheetah_run, tmp_path):
    out = tmp_path / "episode.mp4"
    result = run("render", [f"run={halfcheetah_run}", f"out={out}", "steps=2", "width=64",
                            "height=48"], tmp_path / "cache", tmp_path)
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        assert result.returncode == 2 and "pip install imageio-ffmpeg" in result.stderr
        assert not out.exists()
    elif result.returncode == 0:
        assert out.stat().st_size > 0


@pytest.mark.parametrize("args, words", [
    ([], ["missing argument run="]),
    (["run=/nonexistent/run"], ["no such run directory"]),
    (["policy=best"], ["policy='best'", "mu, td3, elite"]),
    (["out=episode.avi"], [".mp4 or .gif"]),
    (["colour=red"], ["unknown argument 'colour=red'"]),
])
def test_render_bad_arguments(halfcheetah_run, tmp_path, args, words):
    base = [] if args in ([], ["run=/nonexistent/run"]) else [f"run={halfcheetah_run}"]
    result = run("render", base + args, tmp_path / "cache", tmp_path)
    assert result.returncode == 2
    for word in words:
        assert word in result.stderr
    assert "Traceback" not in result.stderr


def test_evaluate_a_mujoco_run(halfcheetah_run, tmp_path):
    result = run("evaluate", [f"run={halfcheetah_run}", "episodes=3"], tmp_path / "cache",
                 tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [l.split() for l in result.stdout.splitlines() if l.startswith("  ")]
    assert [l[0] for l in lines] == ["mu", "td3", "elite"]
    assert all(len(l) == 4 + 3 and np.isfinite(float(l[1])) for l in lines)  # mean ± std, 3 returns
    assert "generation 7" in result.stdout and "3 episodes of 20 steps" in result.stdout

"""`python -m pgps_jax.render run=<dir>`: an MP4 or GIF of one episode of a run's saved actor.

    python -m pgps_jax.render run=runs/halfcheetah/seed0                  # <dir>/episode.mp4
    python -m pgps_jax.render run=runs/hopper/seed0 out=hopper.mp4 steps=500 width=640 height=480

The episode is played on MJX (deterministic actor, start state = the first evaluation episode's,
from PRNGKey(seed + 100)); its positions are then drawn with MuJoCo's offscreen renderer.

Arguments (key=value): run (required); out (.gif or .mp4; default <run>/episode.mp4 when
imageio-ffmpeg is installed, else <run>/episode.gif); policy (an actor the run saved: mu,
td3 or elite of PGPS; default the one it reports); steps (default: the run's eval_steps);
width, height (default 480x360, at most 640x480); camera (a camera name of the model, default
its first one, "track"); max_fps (default 50; faster tasks skip frames).

Headless machines (no display): MuJoCo needs an offscreen OpenGL. The command sets
MUJOCO_GL=egl when neither MUJOCO_GL nor DISPLAY is set (in a process that has not imported
MuJoCo yet; importing this module changes nothing); EGL comes with the system package
`libegl1` (Debian/Ubuntu: `apt-get install libegl1`; with NVIDIA drivers, their EGL). Without
EGL, install OSMesa (`apt-get install libosmesa6`) and run with MUJOCO_GL=osmesa (slower).
MP4 needs `pip install imageio-ffmpeg`; GIF needs nothing more.
"""

import functools
import importlib.util
import math
import os
import pathlib
import sys
from typing import Optional, Sequence

import jax
import numpy as np

from pgps_jax.agent.config import TASK_NAMES
from pgps_jax.cli.errors import EXIT_OK, UsageError, report
from pgps_jax.cli.tool_args import load_run, parse_args, require_writable

_GL_HELP = ("MuJoCo's offscreen rendering needs OpenGL without a display: install EGL "
            "(Debian/Ubuntu: apt-get install libegl1) and set MUJOCO_GL=egl, or OSMesa "
            "(apt-get install libosmesa6) and set MUJOCO_GL=osmesa")


def _import_mujoco():
    try:
        import mujoco
    except Exception as e:  # the GL backend named by MUJOCO_GL failed to load
        raise UsageError(f"cannot load MuJoCo with MUJOCO_GL={os.environ.get('MUJOCO_GL')}: "
                         f"{e}. {_GL_HELP}") from None
    return mujoco


def _episode(agent, flat_actor, key, steps: int):
    """qpos [steps + 1, nq], rewards [steps], dones [steps] of one deterministic episode of
    the agent's env."""
    env, policy = agent.env, agent.policy
    first = env.reset(key)

    def body(state, _):
        state = env.step(state, policy(flat_actor, state.obs))
        return state, (state.pipeline_state.qpos, state.reward, state.done)

    _, (qpos, rewards, dones) = jax.lax.scan(body, first, None, length=steps)
    return (jax.numpy.concatenate([first.pipeline_state.qpos[None], qpos]), rewards, dones)


def render_frames(mj_model, qpos: np.ndarray, width: int, height: int,
                  camera: Optional[str]) -> list[np.ndarray]:
    """RGB frames [height, width, 3] of the model posed at each row of `qpos`."""
    mujoco = _import_mujoco()
    limit = (mj_model.vis.global_.offwidth, mj_model.vis.global_.offheight)
    if width > limit[0] or height > limit[1]:
        raise UsageError(f"width x height = {width}x{height} exceeds the model's offscreen "
                         f"buffer {limit[0]}x{limit[1]}")
    cameras = [mj_model.camera(i).name for i in range(mj_model.ncam)]
    if camera is None:
        camera_id = 0 if cameras else -1
    elif camera in cameras:
        camera_id = cameras.index(camera)
    else:
        raise UsageError(f"camera={camera!r} is not in the model; cameras: {', '.join(cameras)}")
    try:
        renderer = mujoco.Renderer(mj_model, height, width)
    except Exception as e:
        raise UsageError(f"cannot create MuJoCo's offscreen renderer "
                         f"(MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {e}. {_GL_HELP}") from None
    data = mujoco.MjData(mj_model)
    frames = []
    try:
        for q in qpos:
            data.qpos[:] = q
            mujoco.mj_forward(mj_model, data)
            renderer.update_scene(data, camera=camera_id)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
    return frames


def write_video(path: pathlib.Path, frames: Sequence[np.ndarray], fps: float) -> None:
    """An .mp4 (imageio-ffmpeg) or .gif (Pillow) of `frames`."""
    import imageio.v2 as imageio
    suffix = path.suffix.lower()
    if suffix == ".mp4":
        if importlib.util.find_spec("imageio_ffmpeg") is None:
            raise UsageError("writing an MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg); "
                             "or choose out=<name>.gif")
        imageio.mimsave(path, frames, fps=fps, macro_block_size=8)
    elif suffix == ".gif":
        imageio.mimsave(path, frames, duration=1000.0 / fps, loop=0)
    else:
        raise UsageError(f"out={path}: the file name must end in .mp4 or .gif")


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if ("mujoco" not in sys.modules and "MUJOCO_GL" not in os.environ
            and not os.environ.get("DISPLAY")):
        os.environ["MUJOCO_GL"] = "egl"  # read by MuJoCo's first import, in `_render`
    return report(lambda: _render(argv))


def _render(argv: Sequence[str]) -> int:
    args = parse_args(argv, {"run": str, "out": str, "policy": str, "steps": int,
                             "width": int, "height": int, "camera": str, "max_fps": float},
                      __doc__, required=("run",), at_least={"steps": 1})
    settings, config, saved = load_run(args["run"])
    saved_actors = [k for k in saved if k not in ("generation", "env_steps")]
    policy = args.get("policy", saved_actors[0])
    if policy not in saved_actors:
        raise UsageError(f"policy={policy!r}: the run saved {', '.join(saved_actors)}; "
                         "choose one of them")
    steps = args.get("steps", settings.eval_steps)
    default_suffix = ".mp4" if importlib.util.find_spec("imageio_ffmpeg") else ".gif"
    out = pathlib.Path(args.get("out", pathlib.Path(args["run"]) / f"episode{default_suffix}"))
    if out.suffix.lower() not in (".mp4", ".gif"):
        raise UsageError(f"out={out}: the file name must end in .mp4 or .gif")
    if out.suffix.lower() == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise UsageError("writing an MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg); "
                         "or choose out=<name>.gif")
    require_writable(str(out))
    if settings.env not in TASK_NAMES:
        raise UsageError(f"env {settings.env!r} has no MuJoCo model to render; "
                         f"render a run of {', '.join(TASK_NAMES)}")
    _import_mujoco()  # before everything that imports mujoco (brax, the envs)
    from pgps_jax.agent.evaluation import start_keys
    from pgps_jax.agent.algorithms import make_agent
    from pgps_jax.cli import run_physics
    env = run_physics.run_env(args["run"], settings.env, settings.physics)
    # the start state of the run's first test episode
    key = start_keys(jax.random.PRNGKey(settings.seed + 100), 1, settings.eval_episodes)[0]
    qpos, rewards, dones = jax.device_get(
        jax.jit(functools.partial(_episode, make_agent(settings.algo, config, env),
                                  steps=steps))(
            jax.numpy.asarray(saved[policy]), key))
    ended = np.flatnonzero(dones > 0)
    length = int(ended[0]) + 1 if ended.size else steps
    max_fps = args.get("max_fps", 50.0)
    skip = max(1, math.ceil((1.0 / env.dt) / max_fps))
    frames = render_frames(env.mj_model, qpos[:length + 1:skip], args.get("width", 480),
                           args.get("height", 360), args.get("camera"))
    write_video(out, frames, fps=1.0 / (env.dt * skip))
    print(f"wrote {out}: {settings.env}, {policy} of generation {saved['generation']}, "
          f"{length} steps{' (terminated)' if ended.size else ''}, return "
          f"{float(rewards[:length].sum()):.2f}; {len(frames)} frames at "
          f"{1.0 / (env.dt * skip):.1f} fps")
    return EXIT_OK

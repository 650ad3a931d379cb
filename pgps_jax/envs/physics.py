"""MuJoCo models from Brax's assets, their solver settings, and the frame-skip step on MJX.

An env step is `n_frames` calls of `mjx.step`, with the control held fixed (Gym's
`do_simulation`). Nothing else is computed per frame. MJX computes it in JAX (`impl="jax"`,
the default) or with MuJoCo Warp's kernels (`impl="warp"`, where the `warp-lang` package is
installed).
"""

import contextlib
import dataclasses
import functools
import sys

from typing import Optional

import brax
from etils import epath
import jax
import mujoco
from mujoco import mjx
import numpy as np

from pgps_jax.envs import mjx_rewrites
from pgps_jax.envs.mjx_rewrites import fused_solve as fused
from pgps_jax.envs.mjx_rewrites import small_linalg
from pgps_jax.field_types import mismatch

_ASSETS = epath.resource_path(brax.__name__) / "envs/assets"
_SOLVERS = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}
_INTEGRATORS = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
                "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
IMPLS = ("jax", "warp")
"""MJX's implementations: its JAX code, or MuJoCo Warp's kernels called from JAX."""
WARP_CONTACTS_PER_WORLD = 64
"""MuJoCo Warp holds the contacts of every env of a batch in one array: room for this many
per env (the ant, whose 13 geoms touch the floor on Gym's contacts, has the most of the
tasks)."""
WARP_MAX_WORLDS = 4096
"""The envs of a batch whose contacts that array has room for (about 50 MB, allocated
whatever the batch); a larger batch can run out of room, which MuJoCo Warp reports as an
overflow."""
FLOOR_CONTACTS = ("model", "gym")
"""Which geoms touch the floor: those the Brax asset lets (ant: four zero-mass foot spheres
that Brax added), or Gym's: every body geom with a 0.01 m contact margin, the added spheres
removed."""


SPEED_ONLY = ("write_out_linalg", "unroll_line_search", "unroll_solver", "fused_solve")
"""The `Physics` fields that change how a physics step is computed, not what (its results
stay equal to float tolerance)."""
MATMUL_PRECISIONS = ("highest", "default")
"""The precision of the physics' float32 matrix products: float32 ('highest'), or the
platform's default, which on a recent NVIDIA GPU rounds their operands to TF32 (10-bit
mantissas)."""


@dataclasses.dataclass(frozen=True)
class Physics:
    """Constraint-solver settings of one task (MuJoCo `mjOption` fields)."""

    integrator: str = "euler"
    """'euler', 'rk4' (four forward passes per physics step) or 'implicitfast' (damping and
    velocity-dependent forces integrated implicitly, one forward pass)."""
    solver: str = "newton"
    """'newton' or 'cg' (MJX has no PGS)."""
    iterations: int = 1
    """Maximum solver iterations per physics step."""
    ls_iterations: int = 4
    """Maximum line-search iterations per solver iteration (all of them run under vmap)."""
    euler_damping: bool = False
    """Integrate joint damping implicitly in the Euler step (MuJoCo's default: on)."""
    floor_contacts: str = "model"
    """One of `FLOOR_CONTACTS`."""
    write_out_linalg: Optional[bool] = None
    """Small Cholesky factorisations and solves as fused array code (`mjx_rewrites`); None:
    on a GPU for models of up to `small_linalg.MAX_SIZE` degrees of freedom."""
    unroll_line_search: Optional[bool] = None
    """The Newton solver's line search without a device loop (`mjx_rewrites`); None: on a
    GPU. Idle where the fused solve runs."""
    unroll_solver: Optional[bool] = None
    """The solver's iterations, when there are several, without a device loop
    (`mjx_rewrites`); None: on a GPU. Idle where the fused solve runs."""
    matmul_precision: str = "highest"
    """One of `MATMUL_PRECISIONS`. With 'default' an H100's next observations differ from
    float32's by up to 1.3e-2 (relative) after one env step, 350-1,300 times float32's own
    rounding, at no gain in speed (BENCHMARKS.md "The Newton solve as one kernel")."""
    fused_solve: Optional[bool] = None
    """The Newton solve as one kernel per env (`mjx_rewrites.fused_solve`; interpreted off a
    GPU): 1.2-1.9 times shorter env steps on an H100, its states MJX's to float32 rounding
    (on a CPU, and on an H100 for the five tasks). None: on a GPU, for a model it
    covers, with float32 products around it (its own are float32). Where it runs, the
    line-search and solver-loop rewrites have nothing to rewrite."""
    impl: str = "jax"
    """One of `IMPLS`. Warp's solver is MuJoCo's, not MJX's JAX one: solved to convergence
    the two agree, with a truncated solve their states differ beyond float tolerance. The
    `mjx_rewrites` apply to JAX's alone. The agents train on either (`envs.env_batches`)."""

    def model_settings(self) -> dict:
        """The fields that define the simulated physics (all but `SPEED_ONLY`)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in SPEED_ONLY}

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            expected = mismatch(value, field.type)
            if expected:
                raise ValueError(f"{field.name} must be {expected}, got {value!r}")
        if self.integrator not in _INTEGRATORS:
            raise ValueError(f"integrator must be one of {sorted(_INTEGRATORS)}, "
                             f"got {self.integrator!r}")
        if self.impl not in IMPLS:
            raise ValueError(f"impl must be one of {', '.join(IMPLS)}, got {self.impl!r}")
        if self.solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {sorted(_SOLVERS)}, got {self.solver!r}")
        if self.floor_contacts not in FLOOR_CONTACTS:
            raise ValueError(f"floor_contacts must be one of {', '.join(FLOOR_CONTACTS)}, "
                             f"got {self.floor_contacts!r}")
        require_precision(self.matmul_precision, self.fused_solve)
        if self.iterations < 1 or self.ls_iterations < 1:
            raise ValueError(
                f"iterations and ls_iterations must be >= 1, got {self.iterations}, "
                f"{self.ls_iterations}")


def require_precision(matmul_precision: str, fused_solve: Optional[bool]) -> None:
    """ValueError unless `matmul_precision` is one of `MATMUL_PRECISIONS` and, with the fused
    solve (float32) asked for, 'highest'."""
    if matmul_precision not in MATMUL_PRECISIONS:
        raise ValueError(f"matmul_precision must be one of {', '.join(MATMUL_PRECISIONS)}, "
                         f"got {matmul_precision!r}")
    if fused_solve and matmul_precision != "highest":
        raise ValueError("fused_solve computes in float32: with matmul_precision="
                         f"{matmul_precision!r} around it the step would mix two precisions; "
                         "set matmul_precision=highest or fused_solve=false")


def model_defaults(xml: str) -> Physics:
    """The settings written in a Brax asset (MuJoCo's defaults where it names none)."""
    opt = mujoco.MjModel.from_xml_path(str(_ASSETS / xml)).opt
    solver = {v: k for k, v in _SOLVERS.items()}[mujoco.mjtSolver(opt.solver)]
    integrator = {v: k for k, v in _INTEGRATORS.items()}[mujoco.mjtIntegrator(opt.integrator)]
    return Physics(integrator=integrator, solver=solver, iterations=int(opt.iterations),
                   ls_iterations=int(opt.ls_iterations),
                   euler_damping=not opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP)


def load_model(xml: str, physics: Physics) -> tuple[mujoco.MjModel, mjx.Model]:
    """Loads `brax/envs/assets/<xml>` with `physics` applied; returns it and its MJX copy."""
    with _known_warnings_dropped():
        if physics.floor_contacts == "gym":
            spec = mujoco.MjSpec.from_file(str(_ASSETS / xml))
            _gym_floor_contacts(spec)
            model = spec.compile()
        else:
            model = mujoco.MjModel.from_xml_path(str(_ASSETS / xml))
    model.opt.integrator = _INTEGRATORS[physics.integrator]
    model.opt.solver = _SOLVERS[physics.solver]
    model.opt.iterations = physics.iterations
    model.opt.ls_iterations = physics.ls_iterations
    eulerdamp = int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)
    if physics.euler_damping:
        model.opt.disableflags &= ~eulerdamp
    else:
        model.opt.disableflags |= eulerdamp
    if physics.impl != "warp":
        jax_model = mjx.put_model(model, impl="jax")
        if physics.fused_solve:
            fused.refuse_unsupported(jax_model)
        return model, jax_model
    if physics.fused_solve:
        raise ValueError("fused_solve replaces MJX's JAX solver, not Warp's: with impl=warp "
                         "set fused_solve=false")
    _require_warp()
    warp_model = mjx.put_model(model, impl="warp")
    return model, warp_model.tree_replace({"opt._impl.warn_overflow": _warp_overflows_warned(
        warp_model.opt._impl.warn_overflow)})


def _warp_overflows_warned(flags: int) -> int:
    """MuJoCo Warp's overflow warnings less those of the solver's (line search) iterations
    reaching their limit, which a fixed iteration count reaches by design."""
    from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType
    return int(flags) & ~int(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)


def _require_warp() -> None:
    """A RuntimeError that names the missing package unless MuJoCo Warp can run."""
    from mujoco.mjx import warp as mjx_warp
    if not mjx_warp.WARP_INSTALLED:
        raise RuntimeError("impl='warp' needs the warp-lang package: pip install warp-lang "
                           "(or impl='jax', the default)")
    warp = mjx_warp.warp
    warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)  # no line per kernel


def make_data(model: mujoco.MjModel, impl: str) -> mjx.Data:
    """A zero physics state for `model` on the `impl` of `IMPLS`; for Warp, with room for
    `WARP_CONTACTS_PER_WORLD` contacts per env in batches of up to `WARP_MAX_WORLDS` envs."""
    if impl != "warp":
        return mjx.make_data(model, impl="jax")
    return mjx.make_data(model, impl="warp",
                         naconmax=WARP_CONTACTS_PER_WORLD * WARP_MAX_WORLDS,
                         njmax=WARP_CONTACTS_PER_WORLD * 6 + model.nv)  # ≤ 6 rows a contact


def _gym_floor_contacts(spec: mujoco.MjSpec) -> None:
    """Gym's contacts: each geom of a body collides with the world's geoms (the floor), not
    with the others, with a 0.01 m margin; the zero-mass contact spheres that Brax added (the
    ant's feet, which sit on its capsules' end caps) are removed. Set before compiling: the
    compiled model's broad and mid phase only see the geoms that collided then."""
    for geom in [g for g in spec.geoms if g.mass == 0]:
        spec.delete(geom)
    for geom in spec.geoms:
        on_body = geom.parent.name != spec.worldbody.name
        geom.contype, geom.conaffinity = (1, 0) if on_body else (geom.contype, 1)
        geom.margin = 0.01


_KNOWN_WARNINGS = ("compiler attribute 'settotalmass' is deprecated",)
"""MuJoCo's warnings about Brax's assets that change nothing in the model we load (MuJoCo 4
still applies half_cheetah.xml's `settotalmass`)."""


@contextlib.contextmanager
def _known_warnings_dropped():
    """Inside, MuJoCo's warnings that start like one of `_KNOWN_WARNINGS` are dropped; the
    others reach the previous handler (MuJoCo's own, which prints them, if there was none)."""
    previous = mujoco.get_mju_user_warning()

    def handle(message: str) -> None:
        if message.startswith(_KNOWN_WARNINGS):
            return
        if previous is not None:
            previous(message)
        else:
            print(f"WARNING: {message}", file=sys.stderr)

    mujoco.set_mju_user_warning(handle)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


def init_qpos(model: mujoco.MjModel) -> np.ndarray:
    """The model's `init_qpos` custom numeric (Brax's convention) if present, else qpos0."""
    if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, "init_qpos") >= 0:
        return np.array(model.numeric("init_qpos").data)
    return np.array(model.qpos0)


def default_platform() -> str:
    """The platform that programs run on: that of `jax.default_device` where one is set (the
    CPU of a GPU machine, say), else JAX's default backend."""
    device = jax.config.jax_default_device
    if device is None:
        return jax.default_backend()
    return device if isinstance(device, str) else device.platform


def step_frames(model: mjx.Model, data: mjx.Data, n_frames: int,
                write_out_linalg: Optional[bool] = None,
                unroll_line_search: Optional[bool] = None,
                unroll_solver: Optional[bool] = None, fused_solve: Optional[bool] = None,
                matmul_precision: str = "highest") -> mjx.Data:
    """Advances `data` by `n_frames` physics steps with its control held fixed, its matrix
    products at `matmul_precision` (one of `MATMUL_PRECISIONS`, whatever JAX's
    `default_matmul_precision`).

    `write_out_linalg`, `unroll_line_search`, `unroll_solver` and `fused_solve` switch the
    rewrites of `mjx_rewrites` on or off; None gives `Physics`'s defaults for
    `default_platform()` (on an H200: halfcheetah's physics per env step at batch 40 takes
    1.05 ms with the first two instead of 1.33; the ant's env step at batch 60 7.56 ms with
    its solver's iterations written out instead of 10.69).

    The frames are unrolled: on the GPU every trip of a device loop pauses while the host reads
    its condition, which at these batch sizes costs more than the physics between the pauses
    (halfcheetah, batch 10 / 40 on an H200: 1.70 / 1.99 ms per env step in a loop, 1.46 /
    1.50 ms unrolled).
    The price is compiling `n_frames` copies of `mjx.step`. A Warp model takes `mjx.step`
    as it is.
    """
    require_precision(matmul_precision, fused_solve)
    on_gpu = default_platform() == "gpu"
    with jax.default_matmul_precision(matmul_precision):
        if model.impl == mjx.Impl.WARP:
            step = functools.partial(mjx.step, model)
        else:
            switches = _switches(model, on_gpu, write_out_linalg, unroll_line_search,
                                 unroll_solver, fused_solve, matmul_precision)
            step = mjx_rewrites.physics_step(model, *switches, on_gpu)
        return jax.lax.fori_loop(0, n_frames, lambda _, d: step(d), data, unroll=on_gpu)


def resolved(physics: Physics, model: mjx.Model) -> Physics:
    """`physics` with the switches it leaves at None set as `step_frames` sets them for
    `default_platform()` and `model`: what a step computes with (for the record)."""
    on_gpu = default_platform() == "gpu"
    if model.impl == mjx.Impl.WARP:
        return physics
    return dataclasses.replace(physics, **dict(zip(
        ("write_out_linalg", "unroll_line_search", "unroll_solver", "fused_solve"),
        _switches(model, on_gpu, physics.write_out_linalg, physics.unroll_line_search,
                  physics.unroll_solver, physics.fused_solve, physics.matmul_precision))))


def _switches(model: mjx.Model, on_gpu: bool, write_out_linalg: Optional[bool],
              unroll_line_search: Optional[bool], unroll_solver: Optional[bool],
              fused_solve: Optional[bool], matmul_precision: str
              ) -> tuple[bool, bool, bool, bool]:
    """The `mjx_rewrites` switches, those left at None set to `Physics`'s defaults for the
    platform."""
    if write_out_linalg is None:
        write_out_linalg = on_gpu and model.nv <= small_linalg.MAX_SIZE
    if unroll_line_search is None:
        unroll_line_search = on_gpu
    if unroll_solver is None:
        unroll_solver = on_gpu
    if fused_solve is None:
        fused_solve = on_gpu and matmul_precision == "highest" and fused.covers(model)
    return write_out_linalg, unroll_line_search, unroll_solver, fused_solve

"""How closely variants of a task's physics agree with its default over one env step.

From `STEPS` states along a rollout of the task's env (`BATCH` envs after `WARMUP` steps of
uniform random actions), each variant steps the same states under the same actions as the
default; a figure is the difference of the next observation relative to the env's largest
|observation|, and the report gives the largest, the median and the 95th percentile over the
envs and states. The variants:
- `one_ulp`: the default from velocities moved by one unit in the last place, at random: the
  spread that float rounding alone gives;
- `tf32_products`: the task with `matmul_precision=default`, the operands of its float32
  matrix-matrix products rounded to TF32's 10 mantissa bits: what a GPU's tensor cores
  multiply at JAX's default precision; emulated, so meaningful where products are float32
  (a CPU);
- `tf32_solver_products`: the same rounding in the products of MJX's constraint solver alone
  (`SOLVER`);
- each `--variant NAME=VALUE ...` (`make_env` arguments; on a GPU `matmul_precision=default`
  gives its real TF32 products, `fused_solve=false` MJX's own solve).

The reference is the task's default env: on a GPU, with the fused solve.

    python -m benchmarks.step_agreement --tasks walker2d,ant --variant fused_solve=false
    python -m benchmarks.step_agreement --variant matmul_precision=default
"""

import argparse
import contextlib
import json
import sys
from typing import Optional

import jax
from jax._src.lax import lax as lax_internals
import jax.numpy as jnp
import numpy as np

from benchmarks.timing import physics_record, provenance
from pgps_jax.cli.assignments import env_assignments
from pgps_jax.cli.errors import UsageError
from pgps_jax.envs import TASKS, make_env

BATCH, WARMUP, STEPS = 60, 200, 20
SOLVER = "mujoco.mjx._src.solver"
"""The module of MJX's constraint solver."""


def variant_name(arguments: dict) -> str:
    """A variant's name in the results: `fused_solve_True` for {"fused_solve": True}."""
    return "_".join(f"{name}_{value}" for name, value in arguments.items())


def differences(reference, variant, start, key: jax.Array, action_size: int,
                steps: int = STEPS) -> np.ndarray:
    """[steps, envs]: the largest component of |variant's next observation − reference's|
    over the env's largest |reference observation|, one step of each (batched `(state,
    actions) -> state`) from the same `steps` states along `reference`'s rollout from `start`,
    uniform random actions (of `key` folded with 1000 + t, apart from the keys a warm-up from
    `key` would use)."""
    state, out = start, []
    for t in range(steps):
        actions = jax.random.uniform(jax.random.fold_in(key, 1000 + t), (start.obs.shape[0],
                                     action_size), minval=-1.0, maxval=1.0)
        ours, theirs = reference(state, actions), variant(state, actions)
        scale = jnp.maximum(jnp.abs(ours.obs).max(axis=-1), 1e-6)
        out.append(np.asarray(jnp.abs(theirs.obs - ours.obs).max(axis=-1) / scale))
        state = ours
    return np.stack(out)


def _tf32(x: jax.Array) -> jax.Array:
    """x rounded to the nearest value with 10 mantissa bits (TF32's); inf and NaN kept."""
    bits = jax.lax.bitcast_convert_type(x, jnp.uint32)
    bits = (bits + jnp.uint32(0x1000)) & jnp.uint32(0xFFFFE000)
    return jnp.where(jnp.isfinite(x), jax.lax.bitcast_convert_type(bits, jnp.float32), x)


def _traced_within(module: str, frame) -> bool:
    """Whether `frame` or one it was called from runs a function of `module`."""
    while frame is not None:
        if frame.f_globals.get("__name__") == module:
            return True
        frame = frame.f_back
    return False


@contextlib.contextmanager
def tf32_products(within: Optional[str] = None):
    """While open, programs traced multiply float32 matrices (both operands of rank 2 or more
    per env) from TF32-rounded operands unless a product asks for `Precision.HIGHEST`,
    everywhere or only inside functions of the module `within`. JAX's caches are cleared on
    entry and exit, so that the programs traced inside are traced afresh and none outside
    keeps the rounding. Within the context JAX still reuses the trace of a jitted `jnp`
    product of the same shapes, rounded or not: a module's products are told apart from
    others' only where their shapes differ (MJX's solver's Hessian, Jᵀ·D·J, has shapes of its
    own in each task's step)."""
    exact = lax_internals.dot_general

    def rounded(lhs, rhs, dimension_numbers, precision=None, *args, **kwargs):
        highest = lax_internals.canonicalize_precision(precision)
        highest = isinstance(highest, tuple) and jax.lax.Precision.HIGHEST in highest
        if (jnp.ndim(lhs) >= 2 and jnp.ndim(rhs) >= 2 and not highest
                and jnp.result_type(lhs) == jnp.result_type(rhs) == jnp.float32
                and (within is None or _traced_within(within, sys._getframe(1)))):
            lhs, rhs = _tf32(lhs), _tf32(rhs)
        return exact(lhs, rhs, dimension_numbers, precision, *args, **kwargs)
    jax.clear_caches()
    lax_internals.dot_general = rounded
    try:
        yield
    finally:
        lax_internals.dot_general = exact
        jax.clear_caches()


def _one_ulp(step):
    """`step` from velocities moved by −1, 0 or +1 unit in the last place (fixed key)."""
    def moved(state, actions):
        qvel = state.pipeline_state.qvel
        way = jax.random.randint(jax.random.PRNGKey(7), qvel.shape, -1, 2)
        qvel = jnp.where(way == 0, qvel, jnp.nextafter(qvel, way * jnp.inf))
        return step(state.replace(pipeline_state=state.pipeline_state.replace(qvel=qvel)),
                    actions)
    return moved


def measure(task: str, variants: list[dict]) -> dict:
    """The figures of one task: per variant, largest, median and 95th percentile; the
    reference's physics as its step runs it (`physics.resolved`: on a GPU, the fused solve)."""
    env = make_env(task)
    key = jax.random.PRNGKey(1)
    start = jax.jit(jax.vmap(env.reset))(jax.random.split(key, BATCH))
    actions = jax.random.uniform(key, (WARMUP, BATCH, env.action_size), minval=-1.0, maxval=1.0)
    start = jax.jit(lambda s, a: jax.lax.scan(
        lambda s, a: (jax.vmap(env.step)(s, a), None), s, a)[0])(start, actions)

    def compiled(variant_env, wrap=lambda step: step):
        return jax.jit(wrap(jax.vmap(variant_env.step))).lower(start, actions[0]).compile()
    steps = {}
    for name, within in (("tf32_products", None), ("tf32_solver_products", SOLVER)):
        with tf32_products(within):
            steps[name] = compiled(make_env(task, matmul_precision="default"))
    reference = compiled(env)
    steps["one_ulp"] = compiled(env, _one_ulp)
    for variant in variants:
        steps[variant_name(variant)] = compiled(make_env(task, **variant))
    out = {"reference_physics": physics_record(env),
           "done_fraction": float(start.done.mean())}
    for name, step in steps.items():
        d = differences(reference, step, start, key, env.action_size)
        out[name] = {"largest": float(d.max()), "median": float(np.median(d)),
                     "p95": float(np.quantile(d, 0.95))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default=",".join(TASKS))
    parser.add_argument("--variant", nargs="*", default=[], metavar="NAME=VALUE",
                        help="make_env arguments of a variant (one variant per argument)")
    parser.add_argument("--out", default="benchmarks/results/step_agreement.json")
    args = parser.parse_args()
    tasks = args.tasks.split(",")
    unknown = sorted(set(tasks) - set(TASKS))
    if unknown:
        parser.error(f"unknown task(s) {', '.join(unknown)}; choose from {', '.join(TASKS)}")
    try:
        variants = [env_assignments([v], "--variant") for v in args.variant]
    except UsageError as e:
        parser.error(str(e))
    results = {**provenance(), "batch": BATCH, "warmup_steps": WARMUP, "states": STEPS,
               "matmul_precision": jax.config.jax_default_matmul_precision, "tasks": {}}
    for task in tasks:
        results["tasks"][task] = measure(task, variants)
        print(task, json.dumps(results["tasks"][task]), flush=True)
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()

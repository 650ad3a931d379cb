"""Fixtures shared by the test modules: one compilation cache for the session's programs (the
tests' and their CLI subprocesses'), and one reduced training run per MuJoCo task, made on
first use."""

import math
import os
import pathlib

from train_cli import with_fast_compile_flags, run_here

# On a GPU, the workers, their CLI subprocesses and the experiment runner's cells share it.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# The tests' programs, theirs and their CLI subprocesses', compile once and run briefly: XLA
# spends less time optimising them (where this JAX's XLA knows the flags).
os.environ["XLA_FLAGS"] = with_fast_compile_flags(os.environ.get("XLA_FLAGS", ""))

import jax  # noqa: E402  (after XLA_FLAGS)
import pytest  # noqa: E402

from pgps_jax.agent.config import EvaluationConfig  # noqa: E402
from pgps_jax.experiments.paper.runner import Budget  # noqa: E402

# The maths tests compare with float32 numpy; a GPU would otherwise multiply in TF32. (Not
# set on a CPU, which multiplies in float32 anyway, so that the tests' in-process runs and
# their CLI subprocesses compile the same programs and share the compilation cache; set for
# the subprocesses too, which compute what the tests' own programs compute.)
if jax.default_backend() != "cpu":
    os.environ["JAX_DEFAULT_MATMUL_PRECISION"] = "highest"
    jax.config.update("jax_default_matmul_precision", "highest")

REDUCED = ("seed=1", "total_steps=600", "eval_every=200", "checkpoint_every=2",
           "checkpoint_every_s=null",
           "progress=false", "pgps.pop_size=2", "pgps.top_k=1", "pgps.actor_hidden=[16]",
           "pgps.critic_hidden=[16]", "pgps.batch_size=16", "pgps.buffer_size=2000",
           "pgps.warmup_steps=200", "pgps.t_init=20", "pgps.t_max=40", "pgps.t_interval=400",
           "pgps.q_filter_start=400", "pgps.sample_ratio=4", "pgps.ss1_size=8",
           "pgps.ss2_size=16", "eval_episodes=2", "eval_steps=50")
"""A PGPS of 2 actors with small networks, episodes of 20-40 steps, a 200-step warm-up and
a 600-step budget: a few generations on real MJX physics in seconds once compiled; the
Q-filter starts at 400 steps, so it runs too. Checkpoints every two generations, not by the
clock (the tests know which generations have one)."""
REDUCED_PGPS = dict(pop_size=2, top_k=1, actor_hidden=(16,), critic_hidden=(16,),
                    batch_size=16, buffer_size=2000, warmup_steps=200, t_init=20, t_max=40,
                    t_interval=400, q_filter_start=400, sample_ratio=4, ss1_size=8,
                    ss2_size=16)
"""REDUCED's pgps.* settings as PGPSConfig fields."""
REDUCED_CELL = Budget(steps=600, seeds=2, checkpoint_every=2, checkpoint_every_s=math.inf,
                      overrides=tuple(REDUCED_PGPS.items()),
                      evaluation=EvaluationConfig(every=200, episodes=2, steps=50))
"""The experiment runner's budget of a cell of two seeds of REDUCED, checkpointed every two
generations and never by the clock (the tests know which generations have one)."""


REDUCED_PHYSICS = {"ant": ("physics.integrator=euler",)}
"""The reduced runs' physics where a task's own is slow to compile on a CPU: the ant's frames
on Euler's integrator, one forward pass each instead of RK4's four (`test_envs` plays its own
RK4 step)."""


SLOW_MODULES_FIRST = ("test_baselines.py", "test_warp_physics.py", "test_tasks.py",
                      "test_pgps.py", "test_fused_solve.py", "test_couplings.py",
                      "test_jaxpr_rewrite.py", "test_waiting_seeds.py", "test_time_split.py",
                      "test_td3.py", "test_small_linalg.py", "test_landscape.py")
"""The modules of the longest tests outside an xdist group (tens of seconds of compiling
each), slowest first: pytest-xdist hands out the groups first, then the other tests in the
order collected, and with these first the workers end the run on short tests together."""
QUICK_MODULES_LAST = ("test_benchmark_physics.py", "test_buffer.py", "test_cem.py",
                      "test_compile_ahead.py", "test_config.py", "test_field_types.py",
                      "test_paper_report.py", "test_qfilter.py", "test_rollout.py",
                      "test_run_config.py", "test_run_physics.py")
"""Modules of tests of a second or less each: the last ones handed out."""


def pytest_collection_modifyitems(items):
    """`SLOW_MODULES_FIRST`, in that order, then the modules not named, then
    `QUICK_MODULES_LAST`; each module's tests stay together and in their order (every worker
    collects the same order)."""
    def rank(item):
        module = item.path.name
        if module in SLOW_MODULES_FIRST:
            return SLOW_MODULES_FIRST.index(module)
        return len(SLOW_MODULES_FIRST) + (module in QUICK_MODULES_LAST)
    items.sort(key=rank)


def reduced(task: str, *overrides: str) -> list[str]:
    """`env=<task>` with REDUCED, `overrides` replacing settings of the same key."""
    merged = {a.split("=", 1)[0]: a for a in (f"env={task}", *REDUCED)}
    merged.update({a.split("=", 1)[0]: a for a in overrides})
    return list(merged.values())


@pytest.fixture(scope="session")
def cache(tmp_path_factory, worker_id) -> pathlib.Path:
    """JAX's persistent compilation cache of every CLI subprocess of the session, shared by
    the pytest-xdist workers: a program that one test compiled loads from it in the next."""
    root = tmp_path_factory.getbasetemp()
    if worker_id != "master":  # each worker's base is a sibling under the session's
        root = root.parent
    directory = root / "jax_cache"
    directory.mkdir(exist_ok=True)
    return directory


@pytest.fixture(scope="session", autouse=True)
def compilation_cache(cache):
    """The tests' own programs use the same cache: a program that another test (or worker)
    compiled loads from it instead of compiling again."""
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)


HOPPER_RUN = pytest.mark.xdist_group("hopper_run")
"""The tests that use `task_runs("hopper")` run on one worker, which trains it once."""


@pytest.fixture(scope="session")
def task_runs(tmp_path_factory):
    """`task_runs(task)`: (run directory, CompletedProcess) of an uninterrupted reduced run of
    `task` through the training command (in this process; the ant on `REDUCED_PHYSICS`),
    trained on first use."""
    made = {}

    def get(task: str):
        if task not in made:
            work = tmp_path_factory.mktemp(f"run_{task}")
            run_dir = work / "run"
            result = run_here("train", reduced(task, f"run_dir={run_dir}",
                                              *REDUCED_PHYSICS.get(task, ())), work)
            assert result.returncode == 0, result.stderr[-3000:]
            made[task] = run_dir, result
        return made[task]

    return get

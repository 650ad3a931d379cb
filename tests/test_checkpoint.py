"""checkpoint + run_dir: exact TrainState round trip, keep-last-N, atomicity, log truncation."""

import json

import jax
import numpy as np
import pytest

from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.checkpoint import Checkpoints, due
from pgps_jax.agent.config import EvaluationConfig, PGPSConfig
from pgps_jax.envs import make_env
from pgps_jax.cli.errors import UsageError
from pgps_jax.agent.pgps import PGPS, TrainState

TINY = PGPSConfig(pop_size=4, top_k=2, actor_hidden=(8,), critic_hidden=(8,), buffer_size=400,
                  warmup_steps=40, t_init=10, t_max=20, t_interval=100,
                  sample_ratio=2, batch_size=8, ss1_size=4, ss2_size=8, q_filter_start=60)


@pytest.fixture(scope="module")
def setup():
    agent = PGPS(TINY, make_env("point"), EvaluationConfig(steps=10))
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    abstract = jax.eval_shape(agent.init, jax.random.PRNGKey(0))
    return agent, state, abstract


def _equal(a, b) -> bool:
    leaves = jax.tree.leaves(jax.tree.map(
        lambda x, y: bool(np.array_equal(np.asarray(x), np.asarray(y)) and x.dtype == y.dtype), a, b))
    return all(leaves) and jax.tree.structure(a) == jax.tree.structure(b)


def test_round_trip_is_exact_and_keeps_the_last_n(setup, tmp_path):
    _, state, abstract = setup
    checkpoints = Checkpoints(tmp_path / "ckpt", keep=3)
    meta = {"config": {"seed": 0, "pgps": {"pop_size": 4}}, "generation": 5, "logs": {"m": 10}}
    for step in (1, 2, 3, 4, 5):
        checkpoints.save(step, state, {**meta, "generation": step})
    assert checkpoints.steps() == [3, 4, 5] and checkpoints.latest_step() == 5
    restored, restored_meta = checkpoints.restore(5, abstract)
    assert isinstance(restored, TrainState)
    assert _equal(restored, state)  # the buffer, optimiser states, β, counters and key
    assert restored_meta == {**meta, "generation": 5}
    assert checkpoints.meta(4)["generation"] == 4
    checkpoints.close()


def test_a_template_of_the_other_key_kind_is_named_as_such(setup, tmp_path):
    """A state started from raw keys restored into a template of typed keys (and the other
    way round) is refused with the keys named, not as another configuration."""
    agent, state, abstract = setup
    typed = jax.jit(agent.init)(jax.random.key(0))
    typed_abstract = jax.eval_shape(agent.init, jax.random.key(0))
    for saved, template, kinds in ((state, typed_abstract, "raw PRNG keys where the "
                                    "template has typed ones"),
                                   (typed, abstract, "typed PRNG keys where the template "
                                    "has raw ones")):
        checkpoints = Checkpoints(tmp_path / kinds.split()[0], keep=1)
        checkpoints.save(1, saved, {"generation": 1})
        with pytest.raises(UsageError, match=f"the checkpoint holds {kinds}") as err:
            checkpoints.restore(1, template)
        assert "jax.random.key(seed)" in str(err.value)
        assert "another configuration" not in str(err.value)
        checkpoints.close()
    with pytest.raises(UsageError, match="another configuration or version"):
        checkpoints = Checkpoints(tmp_path / "raw", keep=1)
        try:
            checkpoints.restore(1, jax.eval_shape(
                PGPS(TINY.replace(pop_size=6, top_k=3), make_env("point"),
                     EvaluationConfig(steps=10)).init, jax.random.PRNGKey(0)))
        finally:
            checkpoints.close()


def test_a_half_written_checkpoint_is_ignored_and_removed(setup, tmp_path):
    _, state, abstract = setup
    directory = tmp_path / "ckpt"
    checkpoints = Checkpoints(directory, keep=3)
    checkpoints.save(1, state, {"generation": 1})
    checkpoints.close()
    # what a process killed mid-save leaves: orbax's temporary directory, never renamed
    partial = directory / "2.orbax-checkpoint-tmp-1234567"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "junk").write_bytes(b"\0" * 10)
    reopened = Checkpoints(directory, keep=3)
    assert reopened.steps() == [1] and reopened.latest_step() == 1
    assert _equal(reopened.restore(1, abstract)[0], state)
    reopened.save(2, state, {"generation": 2})  # the resumed run's next save
    assert not partial.exists()  # removed by the reopened manager
    assert reopened.steps() == [1, 2] and reopened.meta(2) == {"generation": 2}
    reopened.close()


def test_continuing_from_a_restored_state_matches(setup, tmp_path):
    agent, state, abstract = setup
    step = jax.jit(agent.generation_step)
    checkpoints = Checkpoints(tmp_path / "ckpt")
    checkpoints.save(0, state, {})
    restored, _ = checkpoints.restore(0, abstract)
    a, metrics_a = step(state)
    b, metrics_b = step(restored)
    assert _equal(a, b)
    assert jax.device_get(metrics_a)["td3/critic_loss"] == jax.device_get(metrics_b)["td3/critic_loss"]
    checkpoints.close()


def test_csv_log_reopen_cuts_to_the_checkpointed_size(tmp_path):
    log = rundir.CsvLog(tmp_path / "m.csv", ["a", "b"])
    log.start()
    log.write([1, 0.5])
    log.sync()
    size = log.size()
    log.write([2, float("nan")])
    log.close()
    with open(tmp_path / "m.csv", "a") as f:
        f.write("3,0.12")  # a line cut by SIGKILL
    log = rundir.CsvLog(tmp_path / "m.csv", ["a", "b"])
    log.reopen(size)
    log.write([2, True])
    log.close()
    assert (tmp_path / "m.csv").read_text() == "a,b\n1,0.5\n2,1\n"


def test_csv_log_reopen_refuses_a_shorter_or_different_file(tmp_path):
    log = rundir.CsvLog(tmp_path / "m.csv", ["a", "b"])
    log.start()
    log.close()
    with pytest.raises(UsageError, match="fewer than"):
        rundir.CsvLog(tmp_path / "m.csv", ["a", "b"]).reopen(1000)
    with pytest.raises(UsageError, match="columns"):
        rundir.CsvLog(tmp_path / "m.csv", ["a", "c"]).reopen(4)


def test_cells_keep_full_precision():
    x = np.float32(0.1)
    assert float(rundir.cell(x)) == float(x)
    assert rundir.cell(np.bool_(True)) == "1" and rundir.cell(np.int32(7)) == "7"
    assert rundir.cell(float("nan")) == "nan"


def test_actor_file_round_trip(tmp_path):
    path = tmp_path / rundir.ACTORS
    mu = np.arange(5, dtype=np.float32)
    rundir.save_actors(path, 3, 1234, mu=mu, td3=mu + 1, elite=mu + 2)
    loaded = rundir.load_actors(path)
    assert loaded["generation"] == 3 and loaded["env_steps"] == 1234
    np.testing.assert_array_equal(loaded["elite"], mu + 2)
    assert not list(tmp_path.glob(".*tmp"))  # the temporary file was renamed
    with pytest.raises(UsageError, match="no saved actor"):
        rundir.load_actors(tmp_path / "missing.npz")


def test_write_config_and_read_back(tmp_path):
    directory = rundir.RunDir(tmp_path / "run")
    directory.ensure_writable()
    values = {"pgps": {"actor_hidden": [32, 32]}, "env": {"name": "point"}, "seed": 1}
    directory.write_config(values)
    assert directory.read_config() == values
    assert list(json.loads(json.dumps(directory.read_config()))) == ["env", "seed", "pgps"]


def test_ensure_writable_names_the_directory(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(UsageError, match="cannot write the run directory .*a_file/run"):
        rundir.RunDir(blocker / "run").ensure_writable()


def test_a_checkpoint_is_due_by_generations_or_by_the_clock_each_where_set():
    assert [g for g in range(1, 10) if due(g, 3, None, 0.0)] == [3, 6, 9]
    assert due(1, None, 120.0, 120.0) and not due(1, None, 120.0, 119.9)
    assert due(4, 2, 120.0, 5.0) and due(5, 2, 120.0, 130.0) and not due(5, 2, 120.0, 5.0)
    assert not due(7, None, None, 1e9)

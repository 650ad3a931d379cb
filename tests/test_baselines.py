"""The baselines built from PGPS's parts (CEM alone, TD3 alone, CEM-RL): their presets, their
states, their schedules, and their runs through the training command (the point mass and a
MuJoCo task)."""

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import yaml

from pgps_jax.agent import buffer as replay
from pgps_jax.agent.algorithms import AGENTS, make_agent
from pgps_jax.agent.config import ALGORITHMS, EvaluationConfig, algorithm_preset, for_task
from pgps_jax.agent.metrics import EVALUATION_REPORT, evaluation_metrics, returns_key
from pgps_jax.agent.networks import flatten
from pgps_jax.cli import run_dir as rundir
from pgps_jax.cli.run_config import CONFIG_DIR
from pgps_jax.envs import make_env

from conftest import reduced
from train_cli import cli_env, read_csv, run_here, tiny

SMALL = dict(pop_size=4, top_k=2, actor_hidden=(32, 32), critic_hidden=(32, 32), t_init=20,
             buffer_size=5000, t_max=40, batch_size=32, update_unroll=2)
TESTS = EvaluationConfig(every=200, episodes=2, steps=40)


def agent_of(algo: str, **changes):
    warmup = 0 if algo == "cem" else 100
    config = for_task("hopper", algo, **{**SMALL, "warmup_steps": warmup, **changes})
    return make_agent(algo, config, make_env("point"), TESTS)


def test_the_yaml_presets_are_the_python_ones():
    assert sorted(ALGORITHMS) == sorted(p.stem for p in (CONFIG_DIR / "algo").glob("*.yaml"))
    assert tuple(AGENTS) == ALGORITHMS
    for algo in ALGORITHMS:
        values = yaml.safe_load((CONFIG_DIR / "algo" / f"{algo}.yaml").read_text())
        assert values["algo"] == {"name": algo}
        assert {k: tuple(v) if isinstance(v, list) else v
                for k, v in (values.get("pgps") or {}).items()} == algorithm_preset(algo)


def test_unknown_algorithms_are_refused_with_the_list():
    for make in (lambda: for_task("hopper", "sac"),
                 lambda: make_agent("sac", for_task("hopper"), make_env("point"))):
        with pytest.raises(ValueError, match="unknown algorithm 'sac'; valid: pgps, cem, td3, "
                                             "cemrl"):
            make()
    with pytest.raises(ValueError, match="CEM alone has no replay buffer"):
        agent_of("cem", warmup_steps=100)


def run_generations(agent, generations: int, seed: int = 0):
    state = jax.jit(agent.init)(jax.random.PRNGKey(seed))
    step = jax.jit(agent.generation_step)
    history = []
    for _ in range(generations):
        state, metrics = step(state)
        history.append(jax.device_get(metrics))
    return state, history


@pytest.mark.parametrize("algo", ["cem", "td3", "cemrl"])
def test_each_reports_the_metrics_it_lists(algo):
    agent = agent_of(algo)
    state = jax.eval_shape(agent.init, jax.random.PRNGKey(0))
    _, metrics = jax.eval_shape(agent.generation_step, state)
    listed = [m.key for m in (*agent.generation_metrics(), *EVALUATION_REPORT,
                              *evaluation_metrics(agent.evaluated))]
    listed += [returns_key(a) for a in agent.evaluated]
    assert len(listed) == len(set(listed)) and set(metrics) == set(listed)


def test_cem_alone_never_builds_a_critic_or_a_buffer():
    agent = agent_of("cem")
    state, history = run_generations(agent, 4)
    assert state.td3 is None and state.buffer is None and state.beta is None
    assert not any("td3" in str(path) for path, _ in jax.tree_util.tree_leaves_with_path(state))
    assert int(state.total_steps) == sum(int(m["gen/interaction_steps"]) for m in history)
    # no elitism (CEM-RL's CEM): every slot is a fresh sample; μ moves toward the best
    first = jax.jit(agent.init)(jax.random.PRNGKey(0))
    assert not np.allclose(np.asarray(state.cem.mean), np.asarray(first.cem.mean))


def test_td3_alone_explores_with_its_noise_and_stores_what_it_did():
    agent = agent_of("td3", exploration_noise=0.3)
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    _, played = jax.jit(agent.play)(state)
    steps = int(played.episodes.lengths[0])
    obs = played.transitions.obs[:steps, 0]
    taken = np.asarray(played.transitions.action[:steps, 0])
    greedy = np.asarray(jax.vmap(agent.policy, in_axes=(None, 0))(
        flatten(state.td3.actor), obs))
    inside = np.abs(taken) < 1.0                    # not clipped to the action bounds
    noise = (taken - greedy)[inside]
    assert noise.size > 50 and abs(noise.std() - 0.3) < 0.06 and abs(noise.mean()) < 0.06
    assert np.all(np.asarray(played.valid[:steps, 0])) and not np.any(played.valid[steps:, 0])


def test_td3_alone_plays_its_exploring_episodes_side_by_side_then_updates_once_per_step():
    agent = agent_of("td3", exploring_episodes=2, exploration_noise=0.3)
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    _, played = jax.jit(agent.play)(state)
    lengths = np.asarray(played.episodes.lengths)
    actions = np.asarray(played.transitions.action)
    assert lengths.shape == (2,) and lengths.min() > 10
    assert not np.allclose(actions[:10, 0], actions[:10, 1])    # each its own noise
    learned, metrics = jax.jit(agent.learn)(state, played)
    steps = int(lengths.sum())
    assert int(metrics["gen/interaction_steps"]) == steps
    assert int(learned.total_steps) - int(state.total_steps) == steps
    assert int(learned.buffer.size) - int(state.buffer.size) == steps
    critic_updates = optax.tree_utils.tree_get(learned.td3.critic_opt, "count")
    assert int(critic_updates) == steps
    assert float(metrics["td3/return"]) == pytest.approx(float(played.episodes.returns.mean()))


def test_td3_alone_delays_its_policy_updates():
    """train_delayed = the updates written out one by one: critic updates 0..4, the actor and
    both targets after updates 0, 2 and 4 (d = 2), on the batches it drew."""
    agent = agent_of("td3")
    state = jax.jit(agent.init)(jax.random.PRNGKey(1))
    td3, c = agent.td3, agent.config
    key = jax.random.PRNGKey(7)
    trained, _ = jax.jit(td3.train_delayed, static_argnums=4)(state.td3, state.buffer, key,
                                                              jnp.asarray(5), 8)
    rows_key, noise_key = jax.random.split(key)
    rows = replay.random_rows(state.buffer, rows_key, (8, c.batch_size))
    noise = td3.smoothing_noise(noise_key, (8, c.batch_size, td3.action_size))
    expected = state.td3
    for i in range(5):
        batch = replay.gather(state.buffer, rows[i])
        next_action = td3.target_actions(expected.actor_target, batch.next_obs, noise[i])
        expected, _ = td3.critic_update(expected, batch, next_action, move_target=False)
        if i % 2 == 0:
            expected, _ = td3.actor_update(expected, batch.obs,
                                           jnp.zeros((c.batch_size, td3.action_size)), 0.0)
            expected = td3.move_critic_target(expected)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=2e-5, atol=2e-6),
                 trained, expected)


def test_td3_alone_improves_on_the_point_task():
    agent = agent_of("td3")
    _, history = run_generations(agent, 60)
    tested = [float(m["eval/td3_mean"]) for m in history if m["eval/done"]]
    assert len(tested) >= 4 and tested[-1] > tested[0] + 10


def test_cem_rl_trains_the_first_half_of_the_next_population():
    agent = agent_of("cemrl")
    state = jax.jit(agent.init)(jax.random.PRNGKey(0))
    state, played = jax.jit(agent.play)(state)
    new, _ = jax.jit(agent.learn)(state, played)
    half = agent.num_trained
    sampled = agent.sample(jax.random.split(played.train_key)[0], new.cem)
    after = np.asarray(new.next_population)
    np.testing.assert_allclose(after[half:], np.asarray(sampled[half:]), rtol=1e-5, atol=1e-6)
    moved = np.abs(after[:half] - np.asarray(sampled[:half])).max(axis=1)
    assert np.all(moved > 1e-4)
    np.testing.assert_array_equal(np.asarray(flatten(new.td3.actor)), after[half - 1])


def test_cem_rl_trains_its_actors_as_if_one_after_the_other():
    """The authors' order (`es_grad.py`): for each actor in turn, the critic's block toward
    that actor's target actions, then the actor's S updates against the critic as it stands."""
    agent = agent_of("cemrl")
    td3, c, half = agent.td3, agent.config, agent.num_trained
    state = jax.jit(agent.init)(jax.random.PRNGKey(3))
    state, played = jax.jit(agent.play)(state)
    buffer = replay.add(state.buffer, played.transitions, played.valid)
    key = jax.random.PRNGKey(4)
    actors = agent.sample(jax.random.PRNGKey(5), state.cem)[:half]
    steps = 24
    got, trained, losses = jax.jit(agent.train_half)(state.td3, buffer, key, actors,
                                                     jnp.asarray(steps))

    critic_update, actor_update = jax.jit(td3.critic_update), jax.jit(td3.actor_update)
    expected, ref, critic_total, actor_total = [], state.td3, 0.0, 0.0
    for flat, actor_key in zip(actors, jax.random.split(key, half)):
        actor = agent.actor(flat)
        ref = ref.replace(actor=actor, actor_target=actor,
                          actor_opt=td3.actor_optimizer.init(actor))
        batch_key, noise_key, obs_key = jax.random.split(actor_key, 3)
        for j in range(steps // half):
            batch = replay.sample(buffer, jax.random.fold_in(batch_key, j), c.batch_size)
            noise = td3.smoothing_noise(jax.random.fold_in(noise_key, j),
                                        (c.batch_size, td3.action_size))
            ref, loss = critic_update(ref, batch,
                                      td3.target_actions(ref.actor_target, batch.next_obs, noise))
            critic_total += float(loss)
        for j in range(steps):
            obs = replay.sample_obs(buffer, jax.random.fold_in(obs_key, j), c.batch_size)
            ref, loss = actor_update(ref, obs, jnp.zeros((c.batch_size, td3.action_size)),
                                     jnp.zeros(()))
            actor_total += float(loss)
        expected.append(np.asarray(flatten(ref.actor)))

    assert np.all(np.abs(np.asarray(trained) - np.asarray(actors)).max(axis=1) > 1e-4)
    np.testing.assert_allclose(np.asarray(trained), np.stack(expected), rtol=1e-4, atol=1e-6)
    for name in ("critic", "critic_target", "critic_opt", "actor", "actor_target", "actor_opt"):
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6),
                     getattr(got, name), getattr(ref, name))
    np.testing.assert_allclose(float(losses["td3/critic_loss"]),
                               critic_total / (steps // half * half), rtol=1e-4)
    np.testing.assert_allclose(float(losses["td3/actor_loss"]), actor_total / (steps * half),
                               rtol=1e-4)


@pytest.mark.parametrize("algo", ["cem", "td3", "cemrl"])
def test_each_trains_through_the_command_on_the_point_mass(algo, tmp_path):
    warmup = "pgps.warmup_steps=0" if algo == "cem" else "pgps.warmup_steps=200"
    result = run_here("train", tiny(f"algo={algo}", warmup, "pgps.actor_hidden=[32,32]",
                                    "pgps.critic_hidden=[32,32]", "pgps.batch_size=32",
                                    "total_steps=1500"), tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    run_dir = tmp_path / "runs" / "point" / algo / "seed1"
    agent = AGENTS[algo]
    _, policies = read_csv(run_dir / rundir.EVAL_POLICIES)
    assert list(policies[0]) == rundir.eval_policies_columns(agent.evaluated)
    actors = rundir.load_actors(run_dir / rundir.ACTORS)
    assert [k for k in actors if k not in ("generation", "env_steps")] == list(agent.evaluated)
    _, evals = read_csv(run_dir / rundir.EVAL)
    assert evals[-1]["Mean"] == policies[-1][f"{agent.evaluated[0]}_mean"]


@pytest.mark.parametrize("algo", ["cem", "td3", "cemrl"])
def test_each_trains_on_hopper_and_evaluate_reproduces_its_last_evaluation(algo, tmp_path):
    run_dir = tmp_path / "run"
    warmup = "pgps.warmup_steps=0" if algo == "cem" else "pgps.warmup_steps=200"
    result = run_here("train", reduced("hopper", f"algo={algo}", warmup, f"run_dir={run_dir}",
                                       "pgps.pop_size=4", "pgps.top_k=2"), tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "done:" in result.stdout
    out = tmp_path / "eval.csv"
    evaluated = run_here("evaluate", [f"run={run_dir}", f"out={out}"], tmp_path)
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    header, trained = read_csv(run_dir / rundir.EVAL)
    assert read_csv(out) == (header, [{**trained[-1], "": "0"}])


def test_the_command_refuses_an_unknown_algorithm(tmp_path):
    result = run_here("train", ["env=point", "algo=sac"], tmp_path)
    assert result.returncode == 2
    assert "unknown algo 'sac'; choices: cem, cemrl, pgps, td3" in result.stderr
    result = run_here("train", ["env=point", "algo=cem", "pgps.warmup_steps=10"], tmp_path)
    assert result.returncode == 2 and "CEM alone has no replay buffer" in result.stderr


def test_the_peers_evaluate_on_their_training_steps_until_they_reach_the_budget():
    from benchmarks.peers import env_steps_per_update, evaluations
    for algo, every in (("sac", 10_000), ("ppo", 10_000), ("sac", 50_000), ("ppo", 50_000)):
        num_evals, spacing = evaluations(algo, 1_000_000, every)
        assert spacing % env_steps_per_update(algo) == 0 and every <= spacing < 2 * every
        assert (num_evals - 2) * spacing < 1_000_000 <= (num_evals - 1) * spacing
    assert evaluations("ppo", 1_000_000, 10_000) == (63, 16_384)
    assert evaluations("sac", 1_000_000, 50_000) == (21, 50_048)  # 20 after the first


def test_the_peers_run_seeds_side_by_side_as_each_alone_and_skip_the_done_ones(tmp_path,
                                                                             cache):
    """`benchmarks.peers --concurrent 2`: each seed in a process of its own writes the curve it
    writes alone; a seed with its record is not run again, and is refused to a command of other
    settings; result.json gathers the records.
    (The processes share the session's compilation cache: the second run loads the first's
    programs.)"""
    command = [sys.executable, "-m", "benchmarks.peers", "--algo", "ppo", "--task", "point",
               "--steps", "8192", "--eval-every", "8192", "--out", str(tmp_path)]
    root = pathlib.Path(__file__).parents[1]
    env = cli_env(cache)
    side = subprocess.run(command + ["--seeds", "2", "--concurrent", "2"], cwd=root, env=env,
                          capture_output=True, text=True)
    assert side.returncode == 0, side.stderr
    cell = tmp_path / "figure4" / "point" / "brax_ppo"
    together = {k: (cell / f"seed{k}.csv").read_text() for k in (1, 2)}
    result = json.loads((cell / "result.json").read_text())
    records = [json.loads((cell / f"seed{k}.json").read_text()) for k in (1, 2)]
    assert result["seeds"] == [1, 2] and result["env_steps"] == [8192, 8192]
    assert result["final"]["policy"] == [r["final"] for r in records]
    assert [float(together[k].splitlines()[-1].split(",")[2]) for k in (1, 2)] == \
        result["final"]["policy"]

    (cell / "seed2.json").unlink()
    alone = subprocess.run(command + ["--seeds", "2"], cwd=root, env=env, capture_output=True,
                           text=True)
    assert alone.returncode == 0, alone.stderr
    assert "seed 1:" not in alone.stdout and "seed 2: step 8,192" in alone.stdout
    assert (cell / "seed2.csv").read_text() == together[2]

    from benchmarks.peers import done_seeds, run_settings  # what `--steps 16384` checks
    from pgps_jax.cli.errors import UsageError
    with pytest.raises(UsageError, match="seed 1 .* ran with --steps 8192, this command asks "
                                         "16384"):
        done_seeds(cell, "point", [1, 2], run_settings("point", 16384, 8192, True, {}))


def test_a_peer_seed_counts_as_done_on_the_physics_it_ran_on(tmp_path):
    """A seed recorded before `matmul_precision` existed ran at JAX's default precision: done
    for a command that asks for that physics (its `--env` arguments count through it), refused
    for one on today's float32 products."""
    from benchmarks.peers import done_seeds, run_settings
    from pgps_jax.cli.errors import UsageError
    then = run_settings("hopper", 1000, 500, True, {})
    then["physics"].pop("matmul_precision")
    (tmp_path / "seed1.json").write_text(json.dumps({"run": then}))
    as_then = run_settings("hopper", 1000, 500, True, {"matmul_precision": "default"})
    assert done_seeds(tmp_path, "hopper", [1, 2], as_then) == [1]
    with pytest.raises(UsageError, match="seed 1 .* ran with physics .*'matmul_precision': "
                                         "'default'.* asks .*'matmul_precision': 'highest'"):
        done_seeds(tmp_path, "hopper", [1], run_settings("hopper", 1000, 500, True, {}))


def test_the_peers_name_each_seed_that_failed_in_its_own_process(tmp_path):
    """A seed whose process fails (here: every process given `--seed`, through a
    `sitecustomize`) makes the command fail, naming the seed and its error, and leaves no
    result.json; an unknown task is refused before any seed starts, with the choices."""
    failing = tmp_path / "failing_seeds"
    failing.mkdir()
    (failing / "sitecustomize.py").write_text(
        "import sys\nif '--seed' in sys.argv:\n    raise SystemExit('this seed cannot run')\n")
    path = os.pathsep.join([str(failing), *filter(None, [os.environ.get("PYTHONPATH")])])
    command = [sys.executable, "-m", "benchmarks.peers", "--algo", "ppo", "--steps", "8192",
               "--seeds", "2", "--concurrent", "2", "--out", str(tmp_path)]
    root = pathlib.Path(__file__).parents[1]
    failed = subprocess.run(command + ["--task", "point"], cwd=root, capture_output=True,
                            text=True, env={**os.environ, "JAX_PLATFORMS": "cpu",
                                            "PYTHONPATH": path})
    assert failed.returncode == 1
    assert "2 seed(s) failed" in failed.stderr and "this seed cannot run" in failed.stderr
    assert "seed 1:" in failed.stderr and "seed 2:" in failed.stderr
    assert not (tmp_path / "figure4" / "point" / "brax_ppo" / "result.json").exists()

    unknown = subprocess.run(command + ["--task", "no_such_task"], cwd=root,
                             capture_output=True, text=True,
                             env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert unknown.returncode == 2 and "no_such_task" in unknown.stderr
    assert "halfcheetah" in unknown.stderr and "point" in unknown.stderr

"""Tests of pgps_jax.experiments.landscape on a tiny env whose second observation entry is
always zero."""

import csv

from brax.envs.base import Env, State
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pgps_jax.experiments import landscape
from pgps_jax.cli.errors import UsageError

from train_cli import read_csv, run_here

STEPS = 20
GAMMA = 0.9


class ZeroEntryEnv(Env):
    """1-D mass: obs = [x, 0]; x += 0.1·a with a ∈ [-1, 1]; reward = x; reset x ~ U(0.5, 1).

    Observation entry 1 is always exactly zero, so row 1 of a linear policy's W cannot change
    any action; row 0 can (x > 0 at reset, so the sign and size of W[0, 0] matter).
    """

    def __init__(self):
        self.traces = 0

    def reset(self, rng: jax.Array) -> State:
        self.traces += 1
        x = jax.random.uniform(rng, (), minval=0.5, maxval=1.0)
        zero = jnp.zeros(())
        return State(pipeline_state=None, obs=jnp.stack([x, zero]), reward=zero, done=zero,
                     metrics={"unstable": zero}, info={})

    def step(self, state: State, action: jax.Array) -> State:
        x = state.obs[0] + 0.1 * jnp.clip(action[0], -1.0, 1.0)
        return state.replace(obs=jnp.stack([x, jnp.zeros(())]), reward=x)

    @property
    def observation_size(self) -> int:
        return 2

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "jax"


def _reference_returns(theta: np.ndarray, x0: float) -> tuple[float, float]:
    """Plain numpy episode of ZeroEntryEnv under a = tanh(s·W): (return, discounted)."""
    obs, ret, disc = np.array([x0, 0.0]), 0.0, 0.0
    for t in range(STEPS):
        action = np.tanh(obs @ theta)
        x = obs[0] + 0.1 * np.clip(action[0], -1.0, 1.0)
        ret += x
        disc += GAMMA ** t * x
        obs = np.array([x, 0.0])
    return ret, disc


def test_linear_policy_is_tanh_of_obs_times_w():
    theta = jnp.array([[0.5, -1.0], [2.0, 0.0], [0.0, 3.0]])
    obs = jnp.array([1.0, -0.5, 0.25])
    np.testing.assert_allclose(landscape.linear_policy(theta, obs),
                               np.tanh(np.array([0.5 - 1.0, -1.0 + 0.75])), rtol=1e-6)


def test_sweep_matches_numpy_episodes_and_uses_the_same_seeds_at_every_point():
    env = ZeroEntryEnv()
    theta = jnp.array([[0.3], [0.7]])
    values = jnp.array([-2.0, 0.0, 2.0])
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    sweep = landscape.sweep_parameter(env, theta, jnp.asarray(0), values, keys,
                                      steps=STEPS, gamma=GAMMA)
    chex.assert_shape([sweep.discounted, sweep.returns], (3, 4))
    x0 = np.asarray(jax.vmap(env.reset)(keys).obs[:, 0])
    for i, v in enumerate(np.asarray(values)):
        for s in range(4):
            ret, disc = _reference_returns(np.array([[v], [0.7]]), float(x0[s]))
            np.testing.assert_allclose(sweep.returns[i, s], ret, rtol=1e-5)
            np.testing.assert_allclose(sweep.discounted[i, s], disc, rtol=1e-5)


def test_sweep_of_a_dead_input_is_flat_and_of_a_live_input_is_not():
    env = ZeroEntryEnv()
    theta = jnp.array([[0.2], [0.5]])
    values = jnp.linspace(-3.0, 3.0, 13)
    keys = jax.random.split(jax.random.PRNGKey(1), 5)
    sweep = landscape.make_sweep(env, STEPS, GAMMA)
    dead = sweep(theta, jnp.asarray(1), values, keys)   # W[1,0] multiplies obs[1] == 0
    live = sweep(theta, jnp.asarray(0), values, keys)   # W[0,0] multiplies x > 0
    assert env.traces == 1, "both parameters must share one compiled, batched sweep"
    for curve in (dead.discounted, dead.returns):
        np.testing.assert_array_equal(curve, np.broadcast_to(curve[:1], curve.shape))
    dead_stats = landscape.analyse_curve(values, dead.discounted.mean(1), 0.1, 1e-6)
    live_stats = landscape.analyse_curve(values, live.discounted.mean(1), 0.1, 1e-6)
    assert dead_stats["flat_fraction"] == 1.0 and dead_stats["max_jump"] == 0.0
    # Larger W[0,0] pushes right harder: returns increase with it, by far more than noise.
    assert np.all(np.diff(np.asarray(live.returns.mean(1))) > 0)
    assert live_stats["range"] > 1.0 and live_stats["flat_fraction"] < 1.0


def test_analyse_curve_on_a_step_and_a_line():
    x = np.linspace(0.0, 1.0, 11)
    step = np.where(x < 0.45, 1.0, 5.0)
    stats = landscape.analyse_curve(x, step, flat_tol=0.1, flat_atol=1e-6)
    assert stats["flat_fraction"] == pytest.approx(0.9)    # all but the one jump segment
    assert stats["max_jump"] == pytest.approx(4.0)
    assert stats["max_jump_at"] == pytest.approx(0.45)
    assert stats["max_jump_relative"] == pytest.approx(1.0)
    line = landscape.analyse_curve(x, 3.0 * x, flat_tol=0.1, flat_atol=1e-6)
    assert line["flat_fraction"] == 0.0
    assert line["max_jump"] == pytest.approx(0.3)
    assert line["max_jump_relative"] == pytest.approx(0.1)


def test_resolve_params_default_spread_pairs_and_errors():
    assert landscape.resolve_params(None, (8, 2), 6) == [0, 3, 6, 9, 12, 15]
    assert landscape.resolve_params([5, [3, 1]], (8, 2), 6) == [5, 7]
    with pytest.raises(UsageError, match="sweep.params"):
        landscape.resolve_params([16], (8, 2), 6)
    with pytest.raises(UsageError, match="sweep.params"):
        landscape.resolve_params([[8, 0]], (8, 2), 6)


def test_config_validation_names_the_field():
    with pytest.raises(UsageError, match="sweep.low"):
        landscape.SweepConfig(low=1.0, high=-1.0)
    with pytest.raises(UsageError, match="cem.top_k"):
        landscape.TrainConfig(pop_size=4, top_k=5)


def test_cem_reaches_the_threshold_on_the_tiny_env():
    env = ZeroEntryEnv()
    # Always pushing right (a = 1) returns Σ_t (x0 + 0.1 (t+1)) ≈ 36; pushing left ≈ −6.
    config = landscape.TrainConfig(threshold=30.0, pop_size=8, top_k=4, sigma_init=0.5,
                                   max_generations=30, eval_episodes=2, steps=STEPS)
    result = landscape.train_linear_policy(env, config, jax.random.PRNGKey(0), log=lambda m: None)
    assert result.reached and result.mean_return > 30.0
    assert result.theta.shape == (2, 1) and result.theta[0, 0] > 0  # fitness is maximised


def test_cem_gives_up_with_a_message_and_keeps_the_best():
    env = ZeroEntryEnv()
    config = landscape.TrainConfig(threshold=1e6, pop_size=4, top_k=2, max_generations=2,
                                   eval_episodes=1, steps=STEPS)
    messages = []
    result = landscape.train_linear_policy(env, config, jax.random.PRNGKey(0), messages.append)
    assert not result.reached and result.generations == 2 and np.isfinite(result.mean_return)
    assert "gave up" in messages[-1] and "best" in messages[-1]


def test_run_writes_csvs_figure_params_and_reloads(tmp_path):
    env = ZeroEntryEnv()
    train = landscape.TrainConfig(threshold=30.0, pop_size=8, top_k=4, sigma_init=0.5,
                                  max_generations=30, eval_episodes=2, steps=STEPS)
    sweep = landscape.SweepConfig(low=-1.0, high=1.0, points=5, seeds=3, steps=STEPS,
                                  gamma=GAMMA)
    rows = landscape.run(env, "zero", train, sweep, tmp_path / "a", jax.random.PRNGKey(0),
                         params=[[0, 0], [1, 0]], log=lambda m: None)
    out = tmp_path / "a"
    for name in ("sweep_0_0.csv", "sweep_1_0.csv", "analysis.csv", "landscape.png",
                 "theta.npz"):
        assert (out / name).stat().st_size > 0, name
    with open(out / "sweep_1_0.csv") as f:
        table = list(csv.DictReader(f))
    assert tuple(table[0].keys()) == landscape.CSV_COLUMNS and len(table) == 5
    assert len({r["discounted_mean"] for r in table}) == 1        # the dead input is flat
    with open(out / "analysis.csv") as f:
        analysis = list(csv.DictReader(f))
    assert tuple(analysis[0].keys()) == landscape.ANALYSIS_COLUMNS
    assert [r["parameter"] for r in analysis] == ["W[0,0]", "W[1,0]"]
    assert [r["flat_fraction"] for r in rows][1] == 1.0

    # Reloading the saved W skips training (an unreachable threshold would otherwise give up)
    # and reproduces the sweep exactly.
    never = landscape.TrainConfig(threshold=1e9, max_generations=0, steps=STEPS)
    again = landscape.run(env, "zero", never, sweep, tmp_path / "b", jax.random.PRNGKey(0),
                          params=[[0, 0], [1, 0]], params_file=str(out / "theta.npz"),
                          log=lambda m: None)
    assert (tmp_path / "b" / "sweep_0_0.csv").read_text() == (out / "sweep_0_0.csv").read_text()
    assert again == rows


def test_load_theta_rejects_a_wrong_shape(tmp_path):
    np.savez(tmp_path / "w.npz", theta=np.zeros((3, 1)))
    with pytest.raises(UsageError, match="shape"):
        landscape.load_theta(tmp_path / "w.npz", (2, 1))


@pytest.mark.parametrize("args, words", [
    (["env=cheetahh"], ["unknown env 'cheetahh'", "halfcheetah, hopper, walker2d, ant, swimmer"]),
    (["sweep.points=-3"], ["sweep.points=-3 is invalid", "an integer >= 2"]),
    (["sweep.points=many"], ["sweep.points must be an integer, got 'many'"]),
    (["foo=1"], ["unknown setting 'foo'", "sweep.points"]),
    (["cem.top_k=9", "cem.pop_size=4"], ["cem.top_k=9 is invalid"]),
    (["params_file=missing.npz"], ["params_file=missing.npz: no such file"]),
])
def test_cli_bad_input_is_one_message_and_status_2(tmp_path, args, words):
    result = run_here("landscape", args + [f"output_dir={tmp_path / 'out'}"], tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    for word in words:
        assert word in result.stderr
    assert "Traceback" not in result.stderr and result.stderr.count("error:") == 1
    assert not (tmp_path / "out").exists()


def test_cli_on_a_mujoco_task(tmp_path):
    out = tmp_path / "out"
    result = run_here("landscape", ["env=hopper", "steps=20", "threshold=-1e9",
                                    "cem.pop_size=4", "cem.top_k=2", "cem.eval_episodes=1",
                                    "sweep.num_params=2", "sweep.points=3", "sweep.seeds=2",
                                    f"output_dir={out}"], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    _, rows = read_csv(out / "analysis.csv")
    assert len(rows) == 2
    assert sorted(p.name for p in out.glob("sweep_*.csv")) == sorted(
        f"sweep_{r['row']}_{r['col']}.csv" for r in rows)
    assert (out / "landscape.png").stat().st_size > 0 and (out / "theta.npz").exists()

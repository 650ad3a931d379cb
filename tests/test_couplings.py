"""PGPS's couplings carried in the state: Table 1's five models in one vmapped program train
as each model's own configuration does."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pgps_jax.agent.couplings import SWITCHES, couplings_of
from pgps_jax.agent.pgps import PGPS
from pgps_jax.experiments.paper.grid import cells
from test_pgps import ENV, SMALL, TESTS, programs

pytestmark = pytest.mark.xdist_group("couplings")  # one worker compiles SMALL's program once

MODELS = {cell.config: SMALL.replace(**cell.overrides)
          for cell in cells("table1", tasks=("ant",))}
"""Table 1's cumulative models (Base ... PGPS) as configurations of SMALL."""

COMPARED = ("cem", "td3", "buffer", "beta", "generation", "total_steps", "evaluation", "key")
"""The state's parts every model has (the kept population is one only where Q-filtering is)."""


def stacked(models):
    """The couplings of `models` for SMALL's program, stacked along a leading axis."""
    return jax.tree.map(lambda *s: jnp.stack(s), *[couplings_of(SMALL, m) for m in models])


@pytest.mark.parametrize("name", list(MODELS))
def test_a_model_s_couplings_play_and_learn_as_its_configuration_exactly(name):
    """In SMALL's program (every coupling on), without vmap: the same state and metrics as
    the model's own program; counters, switches and keys exactly, floats to the last bits
    that another program's kernels may change."""
    _, init, step = programs(SMALL, donate=False)  # PGPS(SMALL, ENV, TESTS), jitted
    _, init_alone, step_alone = programs(MODELS[name], donate=False)
    key = jax.random.PRNGKey(7)
    switched = init(key, key + 100, couplings_of(SMALL, MODELS[name]))
    alone = init_alone(key, key + 100)
    for _ in range(6):
        (switched, metrics), (alone, metrics_alone) = step(switched), step_alone(alone)
        assert metrics.keys() == metrics_alone.keys()
        for k in metrics:
            assert_same(metrics[k], metrics_alone[k], k)
    for part in COMPARED + (("kept_population",) if alone.kept_population is not None else ()):
        jax.tree.map(lambda x, y: assert_same(x, y, part),
                     getattr(switched, part), getattr(alone, part))


def assert_same(x, y, what):
    """Equal: exactly unless floating point, then to 1e-5 relative."""
    if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6, err_msg=what)
    else:
        np.testing.assert_array_equal(x, y, err_msg=what)


def test_table1_models_in_one_program_train_as_each_alone():
    agent = PGPS(SMALL, ENV, TESTS)
    keys = jnp.stack([jax.random.PRNGKey(5)] * len(MODELS))  # seed 5 of every model
    states = jax.jit(jax.vmap(agent.init))(keys, keys + 100, stacked(MODELS.values()))
    step = jax.jit(jax.vmap(agent.generation_step))
    together = []
    for _ in range(6):  # Q-filtering starts at 200 steps, in the third generation
        states, metrics = step(states)
        together.append(metrics)
    assert bool(together[-1]["gen/q_filter_active"][list(MODELS).index("pgps")])

    for i, (name, model) in enumerate(MODELS.items()):
        _, init, generation_step = programs(model, donate=False)
        alone = init(jax.random.PRNGKey(5), jax.random.PRNGKey(5) + 100)
        for generation in range(6):
            alone, metrics = generation_step(alone)
            for key in ("td3/in_population", "td3/guided_loss", "gen/episode_limit",
                        "gen/q_filter_active", "gen/total_steps"):
                assert together[generation][key][i] == metrics[key], (name, generation, key)
            for key in metrics:
                np.testing.assert_allclose(together[generation][key][i], metrics[key],
                                           rtol=1e-4, atol=1e-5, err_msg=f"{name}: {key}")
        for part in COMPARED:
            jax.tree.map(lambda x, y: np.testing.assert_allclose(
                x[i], y, rtol=1e-4, atol=1e-5, err_msg=f"{name}: {part}"),
                getattr(states, part), getattr(alone, part))


def test_the_models_differ_where_their_couplings_do():
    """Not a vacuous equality: the switches change what the program computes."""
    _, init, step = programs(SMALL, donate=False)  # PGPS(SMALL, ENV, TESTS), jitted
    base, full = couplings_of(SMALL, MODELS["base"]), couplings_of(SMALL, SMALL)
    a, b = init(jax.random.PRNGKey(5), None, base), init(jax.random.PRNGKey(5), None, full)
    for _ in range(3):
        (a, metrics_a), (b, metrics_b) = step(a), step(b)
    assert int(metrics_a["gen/episode_limit"]) == SMALL.t_max
    assert int(metrics_b["gen/episode_limit"]) < SMALL.t_max
    assert not np.allclose(a.cem.mean, b.cem.mean)


@pytest.mark.parametrize("agent_config, model, message", [
    (MODELS["base"], SMALL, "has pg_guides_ea, ea_guides_pg, q_filter, increasing_steps off"),
    (SMALL, SMALL.replace(pop_size=6), "also differs in pop_size"),
    (SMALL, SMALL.replace(pg_guides_ea=False), "EA→PG without PG→EA"),
    (SMALL.replace(pg_guides_ea=False), MODELS["base"], "EA→PG without PG→EA"),  # a probe
])
def test_couplings_only_switch_off_what_the_program_has(agent_config, model, message):
    with pytest.raises(ValueError, match=message):
        couplings_of(agent_config, model)


def _switches(couplings) -> dict[str, bool]:
    return {s: bool(getattr(couplings, s)) for s in SWITCHES}


def test_a_setting_the_model_leaves_inert_may_differ():
    """Without Q-filtering, resampling before it starts cannot act."""
    model = MODELS["base"].replace(resample_before_q_filter=not SMALL.resample_before_q_filter)
    assert _switches(couplings_of(SMALL, model)) == _switches(couplings_of(SMALL, MODELS["base"]))


def test_a_model_s_couplings_are_its_configuration_s():
    switched = couplings_of(SMALL, MODELS["ea_to_pg"])
    assert _switches(switched) == {
        "pg_guides_ea": True, "ea_guides_pg": True, "q_filter": False,
        "increasing_steps": False}

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

MODELS = {cell.config: SMALL.replace(**cell.overrides)
          for cell in cells("table1", tasks=("ant",))}
"""Table 1's cumulative models (Base ... PGPS) as configurations of SMALL."""

COMPARED = ("cem", "td3", "buffer", "beta", "generation", "total_steps", "evaluation")
"""The state's parts every model has (the kept population is one only where Q-filtering is)."""


def test_table1_models_in_one_program_train_as_each_alone():
    agent = PGPS(SMALL, ENV, TESTS)
    pair = [couplings_of(SMALL, model) for model in MODELS.values()]
    switched = jax.tree.map(lambda *switch: jnp.stack(switch), *pair)
    keys = jnp.stack([jax.random.PRNGKey(5)] * len(MODELS))  # seed 5 of every model
    states = jax.jit(jax.vmap(agent.init))(keys, keys + 100, switched)
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
            np.testing.assert_allclose(together[generation]["td3/return"][i],
                                       metrics["td3/return"], rtol=1e-4, err_msg=name)
        for part in COMPARED:
            jax.tree.map(lambda x, y: np.testing.assert_allclose(
                x[i], y, rtol=1e-4, atol=1e-5, err_msg=f"{name}: {part}"),
                getattr(states, part), getattr(alone, part))


def test_the_models_differ_where_their_couplings_do():
    """Not a vacuous equality: the switches change what the program computes."""
    agent = PGPS(SMALL, ENV, TESTS)
    base, full = couplings_of(SMALL, MODELS["base"]), couplings_of(SMALL, SMALL)
    init, step = jax.jit(agent.init), jax.jit(agent.generation_step)
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
])
def test_couplings_only_switch_off_what_the_program_has(agent_config, model, message):
    with pytest.raises(ValueError, match=message):
        couplings_of(agent_config, model)


def test_a_model_s_couplings_are_its_configuration_s():
    switched = couplings_of(SMALL, MODELS["ea_to_pg"])
    assert {s: bool(getattr(switched, s)) for s in SWITCHES} == {
        "pg_guides_ea": True, "ea_guides_pg": True, "q_filter": False,
        "increasing_steps": False}

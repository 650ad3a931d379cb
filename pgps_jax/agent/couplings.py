"""PGPS's couplings as data: the switches of Table 1's cumulative models carried in the state.

The four couplings of the paper (PG→EA, EA→PG, Q-critic filtering, increasing evaluation
steps) are `PGPSConfig` fields, fixed when a program is traced. A `Couplings` in the
`TrainState` switches them per state instead, so one program trains several of Table 1's
models side by side: vmap `init` over the couplings as over seeds,

    agent = PGPS(for_task("ant"), make_env("ant"))  # every coupling on: the program's shape
    base = for_task("ant", pg_guides_ea=False, ea_guides_pg=False, q_filter=False,
                    increasing_steps=False)  # Table 1's Base model
    models = [base, agent.config]
    switched = jax.tree.map(lambda *s: jnp.stack(s),
                            *[couplings_of(agent.config, m) for m in models])
    pair = jax.vmap(agent.init)(keys, eval_keys, switched)  # keys [2]: one per model

A state's couplings can only switch off what its agent's configuration has on: the
configuration decides the program's shape (the kept population, the TD3 actor's slot). A
state whose couplings equal its configuration's plays and learns as the configuration alone
does; a switch off makes it play and learn as a configuration with that coupling off.
Models trained together play in lockstep: a generation lasts as long as the longest episode
of any of them (Base plays T_max steps from the start, PGPS T_init).
"""

import dataclasses

import chex
import jax
import jax.numpy as jnp

from pgps_jax.agent.config import SWITCHES, PGPSConfig, effective_fields


@chex.dataclass(frozen=True)
class Couplings:
    """[] bool each: PG→EA (the TD3 actor joins the population), EA→PG (the augmented loss
    L^A, eq. 2-3), Q-critic filtering (Algorithm 2) and increasing evaluation steps (eq. 4).
    Made by `couplings_of`, which checks that the agent's program can switch them."""
    pg_guides_ea: jax.Array
    ea_guides_pg: jax.Array
    q_filter: jax.Array
    increasing_steps: jax.Array


def couplings_of(agent_config: PGPSConfig, model: PGPSConfig) -> Couplings:
    """The couplings of configuration `model`, for states of an agent of `agent_config`.

    ValueError, naming the coupling, if `model` differs from `agent_config` in anything but
    the couplings (and settings they leave inert, `effective_fields`), switches on a coupling
    `agent_config` has off, or differs from it in the TD3 actor's own slot (EA→PG without
    PG→EA)."""
    mine, theirs = effective_fields(dataclasses.asdict(model)), dataclasses.asdict(agent_config)
    others = [f for f in mine if f not in SWITCHES and mine[f] != theirs[f]]
    if others:
        raise ValueError(f"couplings only switch {', '.join(SWITCHES)}; the model also "
                         f"differs in {', '.join(others)}")
    on = [f for f in SWITCHES if getattr(model, f) and not getattr(agent_config, f)]
    if on:
        raise ValueError(f"the agent's configuration has {', '.join(on)} off: its program "
                         "cannot switch it on (give the agent a configuration with every "
                         "coupling its states use)")
    if model.td3_probe != agent_config.td3_probe:
        raise ValueError("EA→PG without PG→EA plays the TD3 actor in a slot of its own: "
                         "the model and the agent's configuration must agree on it")
    return Couplings(**{f: jnp.asarray(getattr(model, f), bool) for f in SWITCHES})

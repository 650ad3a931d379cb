"""Episodes of a batch of deterministic actors, and the random-action warm-up.

`run_episodes` plays one episode per actor (Algorithm 3, vmapped over the batch): each lasts
until the task terminates it or it reaches its step limit, with no auto-reset. Its loop stops
as soon as every episode has ended, so short episodes cost short loops.

Episodes can also outlive one loop: `begin_episodes` starts a batch, `play` advances it until
the episodes that `drive` the loop have ended, and the others carry on at the next `play` from
where they stopped (the test episodes that ride along with the population's rollouts).

Termination and truncation: a terminal (unhealthy) step stores discount 0; an episode cut at
its step limit stores discount 1 so the critic bootstraps through it, and so does a step that
the env ends with `info["truncation"]` set (Brax's `EpisodeWrapper` time limit). A step whose
physics went non-finite (`metrics["unstable"]`, or a non-finite observation or reward) ends
the episode and is never marked valid, so it never reaches the replay buffer. An episode whose
reset gives a non-finite observation ends unstable before its first step; in the warm-up,
the step from it is not stored and the env resets again.
"""

from typing import Callable

import chex
import jax
import jax.numpy as jnp

from pgps_jax.agent.buffer import Transition
from pgps_jax.envs import Env, State, env_batches

Policy = Callable[[chex.ArrayTree, jax.Array], jax.Array]  # (params, obs) -> action


@chex.dataclass(frozen=True)
class EpisodeState:
    """A batch of episodes under way (leading dim B on every field)."""
    env: State                # the env state each episode has reached
    limits: jax.Array         # [B] int32 step cap T of each episode
    alive: jax.Array          # [B] bool, still running
    returns: jax.Array        # [B] undiscounted return so far
    discounted: jax.Array     # [B] Σ_t γ^t r_t so far
    lengths: jax.Array        # [B] int32 env steps taken (interaction steps)
    unstable: jax.Array       # [B] bool, the episode ended on a non-finite physics state


@chex.dataclass(frozen=True)
class Episodes:
    returns: jax.Array        # [B] undiscounted return of each episode
    discounted: jax.Array     # [B] Σ_t γ^t r_t with the `gamma` given to run_episodes
    lengths: jax.Array        # [B] int32 env steps taken (interaction steps)
    unstable: jax.Array       # [B] bool, the episode ended on a non-finite physics state
    transitions: Transition   # [max_steps, B, ...] (empty [0, B] when not recorded)
    valid: jax.Array          # [max_steps, B] bool, rows to store in the replay buffer


def _finite(obs: jax.Array) -> jax.Array:
    """[B] bool: every entry of each observation is finite."""
    return jnp.all(jnp.isfinite(obs), axis=-1)


def _is_sound(state: State) -> jax.Array:
    """[B] bool: the step produced finite values and the env did not flag instability."""
    unstable = state.metrics.get("unstable", jnp.zeros_like(state.reward))
    return _finite(state.obs) & jnp.isfinite(state.reward) & (unstable == 0)


def _discount(state: State) -> jax.Array:
    """[B] 0 after a terminal step, 1 otherwise: a step the env cut short by its time limit
    (`info["truncation"]`, as Brax's `EpisodeWrapper` sets it) is not terminal."""
    done = state.done.astype(jnp.float32)
    truncated = state.info.get("truncation")
    if truncated is not None:
        done = done * (1.0 - truncated.astype(jnp.float32))
    return 1.0 - done


def check_reset(env: Env, state: State) -> None:
    """Raises ValueError naming the field if a batch [B] of `reset` states breaks the Env
    contract's shapes: `obs` [observation_size], `reward` and `done` scalars per episode, and
    the physics' controls (`pipeline_state.ctrl`, where it has them) [action_size]."""
    batch = jnp.shape(state.reward)[:1]
    wanted = {"obs": batch + (env.observation_size,), "reward": batch, "done": batch}
    for field, shape in wanted.items():
        found = jnp.shape(getattr(state, field))
        if found != shape:
            raise ValueError(
                f"the env's reset gives {field} of shape {found[1:]} per episode, but the env "
                f"contract needs {shape[1:]} (observation_size {env.observation_size}: a flat "
                "observation vector, a scalar reward and done)")
    controls = getattr(state.pipeline_state, "ctrl", None)
    if controls is not None and jnp.shape(controls)[1:] != (env.action_size,):
        raise ValueError(
            f"the env's physics takes controls of shape {jnp.shape(controls)[1:]} "
            f"(pipeline_state.ctrl) but the env declares action_size {env.action_size}: step "
            "takes the actions as they are, so action_size must be the number of controls")


def check_step_keeps_the_state(before: State, after: State) -> None:
    """Raises ValueError naming what differs if an env's `step` returns a state whose
    structure differs from the one it was given (the Env contract: `reset` and `step` give
    the same `metrics` and `info` keys and array shapes)."""
    for field in ("metrics", "info"):
        was, now = set(getattr(before, field)), set(getattr(after, field))
        if was != now:
            raise ValueError(
                f"the env's step returns {field} keys {sorted(now)} but reset gives "
                f"{sorted(was)}: reset and step must give the same {field} keys (missing from "
                f"step: {sorted(was - now)}; new in step: {sorted(now - was)})")
    if jax.tree.structure(before) != jax.tree.structure(after):
        raise ValueError("the env's step returns a state whose structure differs from "
                         "reset's (pipeline_state fields)")
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(before), jax.tree.leaves(after)):
        was, now = (jnp.shape(x), jnp.result_type(x)), (jnp.shape(y), jnp.result_type(y))
        if was != now:
            raise ValueError(f"the env's step changes {jax.tree_util.keystr(path)} from "
                             f"shape/dtype {was} to {now}; reset and step must agree")


def begin_episodes(env: Env, reset_keys: jax.Array, step_limits: jax.Array) -> EpisodeState:
    """Fresh episodes from `reset_keys` [B]; step_limits [B] caps each (0: the slot stays idle)."""
    batch = reset_keys.shape[0]
    started = jax.vmap(env.reset)(reset_keys)
    check_reset(env, started)
    playing, finite = jnp.asarray(step_limits, jnp.int32) > 0, _finite(started.obs)
    return EpisodeState(env=started,
                        limits=jnp.asarray(step_limits, jnp.int32),
                        alive=playing & finite,
                        returns=jnp.zeros((batch,)), discounted=jnp.zeros((batch,)),
                        lengths=jnp.zeros((batch,), jnp.int32), unstable=playing & ~finite)


def play(env: Env, policy: Policy, params: chex.ArrayTree, episodes: EpisodeState,
         max_steps: int, record: bool = True, gamma: float = 1.0,
         drive: jax.Array | None = None, noise: tuple[jax.Array, jax.Array] | None = None,
         recorded: int | None = None
         ) -> tuple[EpisodeState, Transition, jax.Array, jax.Array]:
    """Steps every live episode until none of those marked in `drive` [B] (default: all) is
    alive; the others advance alongside and may still be alive at the end.

    noise: (key, std [B]): each episode's actions get N(0, std²) noise, clipped to [-1, 1]
    (the TD3 baseline's exploration); the transitions hold the noisy actions.

    Returns the episodes, the transitions [max_steps, R] of the first R = `recorded` episodes
    (default all B; row t = the loop's t-th step; empty [0, R] unless `record`), their
    validity [max_steps, R] and the steps the loop took (int32 []: the most that an episode
    driving it took here; under vmap, each batch's own, while the loop of them all runs as
    long as the longest). The loop takes at most `max_steps` steps: no episode that drives it
    may have more steps left.
    """
    batch = episodes.alive.shape[0]
    recorded = batch if recorded is None else recorded
    drive = jnp.ones((batch,), bool) if drive is None else drive
    act = jax.vmap(policy)
    rows = max_steps if record else 0
    empty = Transition(obs=jnp.zeros((rows, recorded, env.observation_size)),
                       action=jnp.zeros((rows, recorded, env.action_size)),
                       reward=jnp.zeros((rows, recorded)),
                       next_obs=jnp.zeros((rows, recorded, env.observation_size)),
                       discount=jnp.zeros((rows, recorded)))

    def step(c):
        e = c["episodes"]
        state, alive = e.env, e.alive
        action = act(params, state.obs)
        if noise is not None:
            noise_key, std = noise
            perturbation = jax.random.normal(jax.random.fold_in(noise_key, c["t"]), action.shape)
            action = jnp.clip(action + std[:, None] * perturbation, -1.0, 1.0)
        nxt = jax.vmap(env.step)(state, action)
        check_step_keeps_the_state(state, nxt)
        sound = _is_sound(nxt)
        stored = alive & sound
        reward = jnp.where(stored, nxt.reward, 0.0)
        lengths = e.lengths + alive
        e = e.replace(env=env_batches.select(alive, nxt, state), lengths=lengths,
                      returns=e.returns + reward,
                      discounted=e.discounted + gamma ** e.lengths * reward,
                      unstable=e.unstable | (alive & ~sound),
                      alive=stored & (nxt.done == 0) & (lengths < e.limits))
        out = dict(c, t=c["t"] + 1, episodes=e)
        if record:
            row = Transition(obs=state.obs, action=action, reward=nxt.reward,
                             next_obs=nxt.obs, discount=_discount(nxt))
            out["transitions"] = jax.tree.map(lambda buf, x: buf.at[c["t"]].set(x[:recorded]),
                                              c["transitions"], row)
            out["valid"] = c["valid"].at[c["t"]].set(stored[:recorded])
        return out

    carry = dict(t=jnp.zeros((), jnp.int32), episodes=episodes,
                 transitions=empty, valid=jnp.zeros((rows, recorded), bool))
    c = jax.lax.while_loop(lambda c: jnp.any(c["episodes"].alive & drive), step, carry)
    return c["episodes"], c["transitions"], c["valid"], c["t"]


def run_episodes(env: Env, policy: Policy, params: chex.ArrayTree, reset_keys: jax.Array,
                 step_limits: jax.Array, max_steps: int, record: bool = True,
                 gamma: float = 1.0) -> Episodes:
    """One episode per actor; `params` and `reset_keys` have leading batch dim B.

    step_limits: [B] int, each episode's cap T (≤ max_steps); 0 skips that slot.
    record: keep the transitions (population rollouts) or only returns (evaluation).
    gamma: discount of the `discounted` returns (J(s_0) of Appendix A).
    """
    e, transitions, valid, _ = play(env, policy, params,
                                       begin_episodes(env, reset_keys, step_limits), max_steps,
                                       record=record, gamma=gamma)
    return Episodes(returns=e.returns, discounted=e.discounted, lengths=e.lengths,
                    unstable=e.unstable, transitions=transitions, valid=valid)


def random_warmup(env: Env, key: jax.Array, num_envs: int, steps_per_env: int,
                  max_episode_steps: int) -> tuple[Transition, jax.Array]:
    """Uniform random actions in [-1, 1] on `num_envs` envs for `steps_per_env` steps each.

    Episodes restart on termination, instability or after `max_episode_steps` (a truncation,
    stored with discount 1). Returns transitions [steps_per_env, num_envs] and their validity.
    """
    reset_key, action_key, restart_key = jax.random.split(key, 3)
    state = jax.vmap(env.reset)(jax.random.split(reset_key, num_envs))
    check_reset(env, state)

    def step(carry, t):
        state, elapsed = carry
        action = jax.random.uniform(jax.random.fold_in(action_key, t),
                                    (num_envs, env.action_size), minval=-1.0, maxval=1.0)
        nxt = jax.vmap(env.step)(state, action)
        check_step_keeps_the_state(state, nxt)
        sound = _is_sound(nxt) & _finite(state.obs)   # a reset's observation too
        transition = Transition(obs=state.obs, action=action, reward=nxt.reward,
                                next_obs=nxt.obs, discount=_discount(nxt))
        elapsed = elapsed + 1
        restart = (nxt.done > 0) | ~sound | (elapsed >= max_episode_steps)
        fresh = jax.vmap(env.reset)(jax.random.split(jax.random.fold_in(restart_key, t),
                                                     num_envs))
        state = env_batches.select(restart, fresh, nxt)
        return (state, jnp.where(restart, 0, elapsed)), (transition, sound)

    _, (transitions, valid) = jax.lax.scan(step, (state, jnp.zeros((num_envs,), jnp.int32)),
                                           jnp.arange(steps_per_env))
    return transitions, valid

"""TD3 (Fujimoto et al., 2018) as PGPS trains it, with the EA→PG augmented loss.

- Critic: clipped double-Q with target policy smoothing,
  y = r + γ·discount·min_j Q'_j(s', clip(π'(s') + clip(ε, −c, c), −1, 1)), ε ~ N(0, σ²).
- Actor: original loss L^O = E_s[−Q1(s, π(s))] (eq. 1) or augmented loss
  L^A = E_s[−Q1(s, π(s)) + β·D] with D = mean over states and action dims of (π(s) − π_elite(s))²
  (eq. 2).
- β rule (eq. 3): β·2 if D > 1.5·D_target, β/2 if D < D_target/1.5, clamped.
- Schedule (Appendix B): after each generation, `update_blocks` blocks of num_update critic
  updates followed by num_update actor updates; targets move by τ after every update.
- `train_delayed`: the schedule of TD3 itself (Fujimoto et al., 2018, Algorithm 1), for the
  TD3 baseline: every update trains the critic; every `policy_delay`-th also the actor, after
  which both targets move by τ.

Within a block's critic updates π' does not move, and the elite never moves during training,
so `train` computes the smoothed target actions and the elite's actions of a whole block in
a few large batches before its update loops, which then run only what changes each update.
"""

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import optax

from pgps_jax.agent import buffer as replay
from pgps_jax.agent.config import PGPSConfig
from pgps_jax.agent.networks import Actor, TwinCritic, first_q


_PRECOMPUTE_UPDATES = 32
"""Updates whose target (or elite) actions one batched forward pass computes in `train`."""


@chex.dataclass(frozen=True)
class TD3State:
    actor: chex.ArrayTree           # actor parameters (π_TD3)
    actor_target: chex.ArrayTree    # π'
    critic: chex.ArrayTree          # twin critic parameters, leading axis 2 = (Q1, Q2)
    critic_target: chex.ArrayTree   # Q'
    actor_opt: optax.OptState
    critic_opt: optax.OptState


def adapt_beta(beta: jax.Array, distance: jax.Array, d_target: float, beta_min: float,
               beta_max: float) -> jax.Array:
    """Eq. 3: double β if D > 1.5·D_target, halve it if D < D_target/1.5; clamp."""
    beta = jnp.where(distance > 1.5 * d_target, beta * 2.0, beta)
    beta = jnp.where(distance < d_target / 1.5, beta / 2.0, beta)
    return jnp.clip(beta, beta_min, beta_max)


def repeat(num: jax.Array, body, carry, unroll: int):
    """`lax.fori_loop(0, num, body, carry)` for a traced `num`, unrolled `unroll` times.

    Same iterations, same indices, same result; fewer loop trips (each costs a device-side
    condition check between two tiny updates).
    """
    def chunk(j, carry):
        for i in range(unroll):
            carry = body(j * unroll + i, carry)
        return carry

    carry = jax.lax.fori_loop(0, num // unroll, chunk, carry)
    return jax.lax.fori_loop(num // unroll * unroll, num, body, carry)


def action_distance(actions: jax.Array, elite_actions: jax.Array) -> jax.Array:
    """D(π, π_elite): mean over states and action dims of (π(s) − π_elite(s))²."""
    return jnp.mean(jnp.square(actions - elite_actions))


@dataclasses.dataclass(frozen=True)
class TD3:
    """TD3 bound to its static configuration; every method is a pure function."""

    config: PGPSConfig
    observation_size: int
    action_size: int

    @property
    def actor_net(self) -> Actor:
        return Actor(self.action_size, tuple(self.config.actor_hidden))

    @property
    def critic_net(self) -> TwinCritic:
        return TwinCritic(tuple(self.config.critic_hidden))

    def _optimizer(self, lr: float) -> optax.GradientTransformation:
        # PyTorch-style Adam(weight_decay): L2 term added to the clipped gradient, then Adam.
        c = self.config
        clip = (optax.clip_by_global_norm(c.max_grad_norm) if c.max_grad_norm > 0
                else optax.identity())
        return optax.chain(clip, optax.add_decayed_weights(c.weight_decay), optax.adam(lr))

    @property
    def actor_optimizer(self) -> optax.GradientTransformation:
        return self._optimizer(self.config.actor_lr)

    @property
    def critic_optimizer(self) -> optax.GradientTransformation:
        return self._optimizer(self.config.critic_lr)

    def init(self, key: jax.Array) -> TD3State:
        """Fresh actor and twin critic; targets are copies."""
        actor_key, critic_key = jax.random.split(key)
        obs = jnp.zeros((self.observation_size,))
        actor = self.actor_net.init(actor_key, obs)
        critic = self.critic_net.init(critic_key, obs, jnp.zeros((self.action_size,)))
        return TD3State(actor=actor, actor_target=actor, critic=critic, critic_target=critic,
                        actor_opt=self.actor_optimizer.init(actor),
                        critic_opt=self.critic_optimizer.init(critic))

    def smoothing_noise(self, key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
        """Target policy smoothing noise clip(ε, −c, c), ε ~ N(0, σ²), of `shape`."""
        c = self.config
        return jnp.clip(c.policy_noise * jax.random.normal(key, shape), -c.noise_clip,
                        c.noise_clip)

    def target_actions(self, actor_target, next_obs: jax.Array, noise: jax.Array) -> jax.Array:
        """Smoothed target actions clip(π'(s') + noise, −1, 1): [..., action_size]."""
        return jnp.clip(self.actor_net.apply(actor_target, next_obs) + noise, -1.0, 1.0)

    def critic_targets(self, state: TD3State, batch: replay.Transition,
                       next_action: jax.Array) -> jax.Array:
        """y = r + γ·discount·min(Q1', Q2')(s', a'), a' from `target_actions`: [B]."""
        c = self.config
        next_q = self.critic_net.apply(state.critic_target, batch.next_obs, next_action)
        return batch.reward + c.gamma * batch.discount * jnp.min(next_q, axis=0)

    def critic_update(self, state: TD3State, batch: replay.Transition,
                      next_action: jax.Array, move_target: bool = True
                      ) -> tuple[TD3State, jax.Array]:
        """One clipped double-Q step on `batch` with smoothed target actions `next_action`
        [B, action_size], then (if `move_target`) Q' ← τ·Q + (1 − τ)·Q'."""
        target = jax.lax.stop_gradient(self.critic_targets(state, batch, next_action))

        def loss_fn(params):
            q = self.critic_net.apply(params, batch.obs, batch.action)
            return jnp.mean(jnp.square(q - target), axis=1).sum()

        loss, grads = jax.value_and_grad(loss_fn)(state.critic)
        updates, opt = self.critic_optimizer.update(grads, state.critic_opt, state.critic)
        critic = optax.apply_updates(state.critic, updates)
        state = state.replace(critic=critic, critic_opt=opt)
        return (self.move_critic_target(state) if move_target else state), loss

    def move_critic_target(self, state: TD3State) -> TD3State:
        """Q' ← τ·Q + (1 − τ)·Q'."""
        return state.replace(critic_target=optax.incremental_update(
            state.critic, state.critic_target, self.config.tau))

    def actor_loss(self, actor_params, critic_params, obs: jax.Array, elite_actions: jax.Array,
                   beta: jax.Array) -> jax.Array:
        """L^A of eq. 2 (β·D added to −Q1); with β = 0 it is L^O of eq. 1."""
        actions = self.actor_net.apply(actor_params, obs)
        q1 = first_q(self.critic_net, critic_params, obs, actions)
        return -jnp.mean(q1) + beta * action_distance(actions, elite_actions)

    def actor_update(self, state: TD3State, obs: jax.Array, elite_actions: jax.Array,
                     beta: jax.Array) -> tuple[TD3State, jax.Array]:
        """One step on L^A (β > 0) or L^O (β = 0), then π' ← τ·π + (1 − τ)·π'."""
        loss, grads = jax.value_and_grad(self.actor_loss)(state.actor, state.critic, obs,
                                                          elite_actions, beta)
        updates, opt = self.actor_optimizer.update(grads, state.actor_opt, state.actor)
        actor = optax.apply_updates(state.actor, updates)
        actor_target = optax.incremental_update(actor, state.actor_target, self.config.tau)
        return state.replace(actor=actor, actor_target=actor_target, actor_opt=opt), loss

    def train(self, state: TD3State, buffer: replay.BufferState, key: jax.Array,
              num_update: jax.Array, max_update: int, elite_actor, guided: jax.Array,
              beta: jax.Array) -> tuple[TD3State, jax.Array, dict]:
        """Appendix B schedule: `update_blocks` × [num_update critic, num_update actor updates].

        When `guided` (the TD3 actor fell behind), each block draws SS_2 and adapts β (eq. 3)
        from D on it, before its updates or after them (`beta_adapted`), and trains the actor
        on L^A toward `elite_actor`; otherwise on L^O.
        `max_update` (static) bounds num_update: each block draws the rows and the smoothing
        noise of up to that many updates in one go, and computes their target actions (and,
        when guided, the elite's actions) in batches of `_PRECOMPUTE_UPDATES` updates, keeping
        all of that out of the update loops. Returns the new state, the new β and mean losses.
        """
        c = self.config
        batches = (max_update, c.batch_size)

        def in_batches(fn, *per_update):        # fn over [max_update, B, ...] inputs
            return jax.lax.map(lambda xs: fn(*xs), per_update, batch_size=_PRECOMPUTE_UPDATES)

        def block(b, carry):
            state, beta, critic_total, actor_total = carry
            ss2_key, critic_key, noise_key, actor_key = jax.random.split(
                jax.random.fold_in(key, b), 4)
            ss2 = replay.sample_obs(buffer, ss2_key, c.ss2_size)
            elite_on_ss2 = self.actor_net.apply(elite_actor, ss2)

            def adapted(beta, actor):
                distance = action_distance(self.actor_net.apply(actor, ss2), elite_on_ss2)
                return jnp.where(guided, adapt_beta(beta, distance, c.d_target, c.beta_min,
                                                    c.beta_max), beta)

            if c.beta_adapted == "before_block":
                beta = adapted(beta, state.actor)
            critic_rows = replay.random_rows(buffer, critic_key, batches)
            noise = self.smoothing_noise(noise_key, batches + (self.action_size,))
            next_actions = in_batches(functools.partial(self.target_actions, state.actor_target),
                                      buffer.data.next_obs[critic_rows], noise)
            actor_rows = replay.random_rows(buffer, actor_key, batches)
            weight = jnp.where(guided, beta, 0.0)

            def critic_step(i, carry):
                state, total = carry
                state, loss = self.critic_update(state, replay.gather(buffer, critic_rows[i]),
                                                 next_actions[i])
                return state, total + loss

            state, critic_total = repeat(num_update, critic_step, (state, critic_total),
                                         c.update_unroll)
            elite_actions = jax.lax.cond(
                guided, lambda: in_batches(functools.partial(self.actor_net.apply, elite_actor),
                                           buffer.data.obs[actor_rows]),
                lambda: jnp.zeros(batches + (self.action_size,)))

            def actor_step(i, carry):
                state, total = carry
                state, loss = self.actor_update(state, buffer.data.obs[actor_rows[i]],
                                                elite_actions[i], weight)
                return state, total + loss

            state, actor_total = repeat(num_update, actor_step, (state, actor_total),
                                        c.update_unroll)
            if c.beta_adapted == "after_block":
                beta = adapted(beta, state.actor)
            return state, beta, critic_total, actor_total

        zero = jnp.zeros((), jnp.float32)
        state, beta, critic_total, actor_total = jax.lax.fori_loop(
            0, c.update_blocks, block, (state, beta, zero, zero))
        count = jnp.maximum(num_update * c.update_blocks, 1).astype(jnp.float32)
        return state, beta, {"td3/critic_loss": critic_total / count,
                             "td3/actor_loss": actor_total / count}

    def train_delayed(self, state: TD3State, buffer: replay.BufferState, key: jax.Array,
                      num_update: jax.Array, max_update: int) -> tuple[TD3State, dict]:
        """TD3's own schedule (Fujimoto et al., 2018, Algorithm 1): `num_update` updates on
        batches of the buffer, each training the critic toward targets from the current π';
        updates 0, d, 2d, … (d = `policy_delay`) then train the actor on L^O (eq. 1) on the
        same batch and move both targets by τ. `max_update` (static) bounds num_update.
        Returns the new state and the mean losses."""
        c = self.config
        delay = c.policy_delay
        rows_key, noise_key = jax.random.split(key)
        rows = replay.random_rows(buffer, rows_key, (max_update, c.batch_size))
        noise = self.smoothing_noise(noise_key, (max_update, c.batch_size, self.action_size))
        no_elite = jnp.zeros((c.batch_size, self.action_size))

        def policy_step(state, obs):
            state, loss = self.actor_update(state, obs, no_elite, jnp.zeros(()))
            return self.move_critic_target(state), loss

        def update(i, carry, actor_turn):
            state, critic_total, actor_total = carry
            batch = replay.gather(buffer, rows[i])
            next_action = self.target_actions(state.actor_target, batch.next_obs, noise[i])
            state, critic_loss = self.critic_update(state, batch, next_action,
                                                    move_target=False)
            if actor_turn is None:          # the turn known only at run time
                state, actor_loss = jax.lax.cond(
                    i % delay == 0, policy_step,
                    lambda state, obs: (state, jnp.zeros((), jnp.float32)), state, batch.obs)
            elif actor_turn:
                state, actor_loss = policy_step(state, batch.obs)
            else:
                actor_loss = 0.0
            return state, critic_total + critic_loss, actor_total + actor_loss

        # Chunks of a multiple of d updates: within one, whose turn it is is known statically.
        unroll = delay * max(1, c.update_unroll // delay)

        def chunk(j, carry):
            for p in range(unroll):
                carry = update(j * unroll + p, carry, actor_turn=p % delay == 0)
            return carry

        zero = jnp.zeros((), jnp.float32)
        carry = jax.lax.fori_loop(0, num_update // unroll, chunk, (state, zero, zero))
        state, critic_total, actor_total = jax.lax.fori_loop(
            num_update // unroll * unroll, num_update,
            lambda i, carry: update(i, carry, actor_turn=None), carry)
        actor_updates = (num_update + delay - 1) // delay
        return state, {"td3/critic_loss": critic_total / jnp.maximum(num_update, 1),
                       "td3/actor_loss": actor_total / jnp.maximum(actor_updates, 1)}

"""What every algorithm of the package shares: the `TrainState` pytree, the agent's interface
(`Agent`: pure `init`, `play`, `learn`, `generation_step`, `evaluate`) and the rollout that
carries the test evaluation along (Section 5.1).

An algorithm is a frozen dataclass bound to a configuration, an env and the evaluation's
settings. It searches over, or trains, actors of one network (`networks.Actor`, as flat
parameter vectors) and fills the parts of the TrainState it uses; the others stay None. A
generation is `play` (the generation's episodes) then `learn` (what it does with them), so
that one run loop, one checkpoint format and one experiment runner serve every algorithm.
"""

import dataclasses
import functools
from typing import Callable, ClassVar

import chex
import jax
import jax.numpy as jnp

from pgps_jax.agent import buffer as replay
from pgps_jax.agent import evaluation
from pgps_jax.agent.cem import CEMState
from pgps_jax.agent.config import EvaluationConfig, PGPSConfig, check_for_algorithm
from pgps_jax.agent.couplings import Couplings
from pgps_jax.agent.evaluation import EvaluationState
from pgps_jax.agent.metrics import Metric
from pgps_jax.agent.networks import actor_flattener
from pgps_jax.agent.rollout import EpisodeState, begin_episodes, play, random_warmup
from pgps_jax.agent.td3 import TD3, TD3State
from pgps_jax.envs import Env, env_batches


@chex.dataclass(frozen=True)
class TrainState:
    """Everything that changes during training; the parts an algorithm does not use are None
    (CEM alone has no critic, buffer or β; TD3 alone has no search distribution)."""
    generation: jax.Array        # [] int32 generations completed
    total_steps: jax.Array       # [] int32 env steps so far, warm-up included
    evaluation: EvaluationState  # the test evaluation under way, and when the next is due
    key: jax.Array               # PRNG key
    cem: CEMState | None = None      # μ, Σ, damping, elite (flat actor vectors [P])
    td3: TD3State | None = None          # actor, twin critic, targets, optimiser states
    buffer: replay.BufferState | None = None  # device replay buffer
    beta: jax.Array | None = None        # [] distance weight β of L^A (eq. 2-3), persists
    kept_population: jax.Array | None = None
    """[N, P] the population kept until Q-filtering starts (PGPS by default,
    `PGPSConfig.keeps_population`; None: resampled every generation, as is a state whose own
    Q-filtering is switched off, which leaves it unused)."""
    next_population: jax.Array | None = None
    """[N, P] the population the next generation plays, drawn (and half of it trained) at
    the end of this one (CEM-RL)."""
    couplings: Couplings | None = None
    """PGPS's couplings switched by this state (`pgps_jax.agent.couplings.couplings_of`);
    None: as its agent's configuration has them."""


@chex.dataclass(frozen=True)
class Played:
    """What a generation's episodes leave for its learning phase (`play` → `learn`)."""
    population: jax.Array        # [N, P] the actors that played (CEM ranks them)
    episodes: EpisodeState       # [N'] their episodes (N' = N, +1 with PGPS's TD3 probe)
    transitions: replay.Transition  # [t_max, N'] what they met, row by loop step
    valid: jax.Array             # [t_max, N'] rows to store in the buffer
    limit: jax.Array             # [] int32 the episode limit T of this generation
    rollout_steps: jax.Array     # [] int32 sequential env steps of the rollout (`rollout`)
    td3_turn: jax.Array          # [] bool, the TD3 actor played
    train_key: jax.Array         # PRNG key of the generation's learning
    evaluation: evaluation.Report  # the test evaluation, if one ended in this rollout


@dataclasses.dataclass(frozen=True, eq=False)
class Agent:
    """The interface of every algorithm; subclasses define `init`, `play`, `learn`,
    `evaluated_actors` and `generation_metrics`. Methods are pure: jit, vmap, donation and
    sharding are the caller's choice."""

    config: PGPSConfig
    env: Env
    evaluation_config: EvaluationConfig = EvaluationConfig()
    """When and how long the test episodes run (Section 5.1)."""
    td3: TD3 = dataclasses.field(init=False)
    """The actor and critic networks and their updates (used for the actor network alone by
    the algorithms without a critic)."""
    num_params: int = dataclasses.field(init=False)
    """P, the length of a flat actor vector."""
    _unflatten: Callable = dataclasses.field(init=False, repr=False)

    name: ClassVar[str]
    """The algorithm's name (`algo=<name>`)."""
    evaluated: ClassVar[tuple[str, ...]]
    """The actors each test evaluation plays, in `evaluated_actors` order; the first is the
    one the algorithm reports (`eval.csv`, the experiments' curves)."""

    def __post_init__(self):
        check_settings_types(type(self).__name__, self.config, self.evaluation_config)
        check_for_algorithm(self.name, self.config)
        td3 = TD3(self.config, self.env.observation_size, self.env.action_size)
        num_params, unflatten = actor_flattener(td3.actor_net, self.env.observation_size)
        object.__setattr__(self, "td3", td3)
        object.__setattr__(self, "num_params", num_params)
        object.__setattr__(self, "_unflatten", unflatten)

    def init(self, key: jax.Array, eval_key: jax.Array | None = None) -> TrainState:
        raise NotImplementedError

    def play(self, state: TrainState, active: jax.Array | bool = True
             ) -> tuple[TrainState, Played]:
        """The generation's episodes. `active` False: none of them plays a step (a seed
        of a batch that waits this generation out, `pgps_jax.cli.loop`)."""
        raise NotImplementedError

    def learn(self, state: TrainState, played: Played) -> tuple[TrainState, dict]:
        raise NotImplementedError

    def evaluated_actors(self, state: TrainState) -> jax.Array:
        """[A, P]: the actors of `evaluated`, in that order."""
        raise NotImplementedError

    def generation_metrics(self) -> tuple[Metric, ...]:
        """The metrics `learn` reports per generation (besides the evaluation's), in
        metrics.csv's order."""
        raise NotImplementedError

    def generation_step(self, state: TrainState) -> tuple[TrainState, dict]:
        """One generation: `play`, then `learn`. Returns the next state and the generation's
        metrics (`pgps_jax.agent.metrics`)."""
        return self.learn(*self.play(state))

    def policy(self, flat: jax.Array, obs: jax.Array) -> jax.Array:
        """The deterministic action of the flat actor vector `flat` [P] at `obs`."""
        return self.td3.actor_net.apply(self._unflatten(flat), obs)

    def actor(self, flat: jax.Array):
        """The actor network's parameters of a flat actor vector [P]."""
        return self._unflatten(flat)

    # --- shared parts of init and play -------------------------------------------------
    def random_warmup(self, key: jax.Array) -> tuple[replay.BufferState, int]:
        """A buffer filled by `warmup_steps` uniform-random-action steps on `pop_size` envs
        side by side, and the env steps taken."""
        config, env = self.config, self.env
        buffer = replay.init(config.buffer_size, env.observation_size, env.action_size)
        if config.warmup_steps == 0:
            return buffer, 0
        steps_per_env = config.warmup_steps_per_env
        transitions, valid = random_warmup(env, key, config.pop_size, steps_per_env,
                                           config.t_max)
        return replay.add(buffer, transitions, valid), steps_per_env * config.pop_size

    def idle_evaluation(self, actors: jax.Array, key: jax.Array,
                        eval_key: jax.Array | None) -> EvaluationState:
        """No test evaluation under way; the first falls due at once. eval_key: start states
        of every evaluation (the paper uses seed + 100), by default derived from `key`."""
        eval_key = jax.random.fold_in(key, 100) if eval_key is None else eval_key
        return evaluation.idle(self.evaluation_config, self.env, actors, eval_key)

    def rollout(self, state: TrainState, actors: jax.Array, limits: jax.Array,
                reset_key: jax.Array, rows: int, record: bool = True,
                exploration: tuple[jax.Array, jax.Array] | None = None,
                active: jax.Array | bool = True
                ) -> tuple[TrainState, EpisodeState, replay.Transition, jax.Array,
                           jax.Array, evaluation.Report]:
        """One episode of each of `actors` [B, P] (step limits [B]) from fresh start states,
        with the test episodes of the evaluation under way (begun here if due) in extra
        slots that do not drive the loop (they add no sequential env steps).

        exploration: (key, std [B]): Gaussian noise of that std on each actor's actions.
        active: False plays no step (every limit 0, the evaluation not hurried).
        Returns `state` with its evaluation advanced, the actors' episodes, their
        transitions [rows, B] (empty unless `record`) and validity, the sequential env steps
        the rollout took (its longest episode, or the test episodes it had to finish before
        the next evaluation falls due), and the evaluation's report.
        """
        env, tested = self.env, self.evaluation_config
        num_rollout = actors.shape[0]
        tests = evaluation.begin_if_due(tested, env, state.evaluation,
                                        self.evaluated_actors(state), state.total_steps)
        limits = jnp.where(active, limits, 0)
        episodes = begin_episodes(env, jax.random.split(reset_key, num_rollout), limits)
        num_tests = tests.episodes.alive.shape[0]
        test_slots = jnp.arange(num_rollout + num_tests) >= num_rollout
        hurry = evaluation.must_end_now(tests, state.total_steps + limits.sum()) & active
        noise = None
        if exploration is not None:
            noise_key, std = exploration
            noise = (noise_key, jnp.concatenate([std, jnp.zeros((num_tests,))]))
        batch, transitions, valid, rollout_steps = play(
            env, self.policy,
            jnp.concatenate([actors, evaluation.repeat_actors(tests.actors, tested.episodes)]),
            env_batches.concatenate(episodes, tests.episodes),
            max(self.config.t_max, tested.steps),
            record=record, drive=~test_slots | hurry, noise=noise, recorded=num_rollout)
        tests, report = evaluation.advanced(
            tests, env_batches.rows(batch, num_rollout))
        mine = lambda x: x[:rows]
        return (state.replace(evaluation=tests),
                env_batches.rows(batch, 0, num_rollout),
                jax.tree.map(mine, transitions), mine(valid), rollout_steps, report)

    def counters_and_evaluation(self, state: TrainState, played: Played) -> dict:
        """The metrics every algorithm reports: the generation's counters (of the state it
        led to), its episodes that physics cut short, and the test evaluation's report."""
        report = played.evaluation
        return {"gen/generation": state.generation,
                "gen/total_steps": state.total_steps,
                "gen/episode_limit": played.limit,
                "gen/interaction_steps": played.episodes.lengths.sum(),
                "gen/rollout_steps": played.rollout_steps,
                "pop/unstable_episodes": played.episodes.unstable.sum(),
                "eval/done": report.done,
                "eval/step": report.step,
                **evaluation.metrics(report.returns, self.evaluated)}

    # --- checks -----------------------------------------------------------------------
    def check_state(self, state: TrainState) -> None:
        """Raises ValueError, naming what differs, if `state` (or a batch of states) was made
        by an agent of another env, network, population, buffer or evaluation size, or by
        another algorithm."""
        found = {"parameter count": state.evaluation.actors.shape[-1],
                 "observation_size": state.evaluation.episodes.env.obs.shape[-1]}
        wanted = {"parameter count": self.num_params,
                  "observation_size": self.env.observation_size}
        if state.buffer is not None:
            found["action_size"] = state.buffer.data.action.shape[-1]
            wanted["action_size"] = self.env.action_size
        differ = [f"{k} {found[k]} (this agent: {wanted[k]})" for k in found
                  if found[k] != wanted[k]]
        if differ:
            raise ValueError("the TrainState was made for another env or network: "
                             + ", ".join(differ))
        fields = _fields_differing(state, self._state_shapes)
        if fields:
            raise ValueError(f"the TrainState was made by another algorithm or version: {fields}")
        differ = _shapes_differing(state, self._state_shapes)
        if differ:
            raise ValueError("the TrainState was made by an agent of other sizes (population, "
                             "networks, buffer or evaluation): " + "; ".join(differ))

    def unfilled(self) -> "Agent":
        """This agent without the random warm-up: its `init` gives the same shapes, without
        tracing the warm-up's physics (for `jax.eval_shape`)."""
        return dataclasses.replace(self, config=self.config.replace(warmup_steps=0))

    @functools.cached_property
    def _state_shapes(self) -> TrainState:
        """The shapes of the states this agent makes (`init`'s), traced once."""
        return jax.eval_shape(self.unfilled().init, jax.ShapeDtypeStruct((2,), jnp.uint32))

    def _sizes(self) -> str:
        return (f"observation_size {self.env.observation_size}, action_size "
                f"{self.env.action_size}, hidden layers {list(self.config.actor_hidden)}")

    # --- evaluation -------------------------------------------------------------------
    def evaluate(self, actors: "TrainState | jax.Array", key: jax.Array | None = None,
                 names: tuple[str, ...] | None = None) -> dict:
        """Deterministic test episodes (Section 5.1), now: of a state's `evaluated` actors, or
        of any `actors` [A, P].

        Each plays `evaluation_config.episodes` episodes of `.steps` steps, all in one batch,
        from the start states of `key` — by default a state's evaluation key, giving the
        episodes of the evaluations that ride along in training. The metrics name the actors
        by `names`; by default those of `evaluated` where there are as many actors (a state's
        or an evaluation's snapshot), else `actor0`, `actor1`, ….
        """
        if isinstance(actors, TrainState):
            if jnp.ndim(actors.generation):
                raise ValueError("evaluate takes one TrainState, not a batch of them: vmap it "
                                 "over the batch")
            self.check_state(actors)
            key = actors.evaluation.key if key is None else key
            actors = self.evaluated_actors(actors)
        elif key is None:
            raise ValueError("evaluating an array of actors needs the key of the start states")
        elif jnp.ndim(actors) != 2:
            raise ValueError(f"the actors must be an array [A, P], got shape {jnp.shape(actors)}")
        elif jnp.shape(actors)[-1] != self.num_params:
            raise ValueError(f"the actors have {jnp.shape(actors)[-1]} parameters but this "
                             f"agent's actor has {self.num_params} ({self._sizes()})")
        num_actors = jnp.shape(actors)[0]
        if names is None:
            names = (self.evaluated if num_actors == len(self.evaluated)
                     else tuple(f"actor{i}" for i in range(num_actors)))
        elif (not isinstance(names, (tuple, list))
              or not all(isinstance(n, str) and n for n in names)
              or len(set(names)) != len(names)):
            raise ValueError(f"names must be a tuple of distinct non-empty strings, got "
                             f"{names!r}")
        if len(names) != num_actors or not num_actors:
            raise ValueError(f"{len(names)} names {tuple(names)} for {num_actors} actors "
                             "(at least one)")
        returns = evaluation.evaluate(self.evaluation_config, self.env, self.policy, actors,
                                      key)
        return evaluation.metrics(returns, tuple(names))


def check_settings_types(agent: str, config, evaluation_config) -> None:
    """Raises TypeError naming the argument of `agent` that is not a PGPSConfig or an
    EvaluationConfig."""
    for name, value, kind in (("config", config, PGPSConfig),
                              ("evaluation_config", evaluation_config, EvaluationConfig)):
        if not isinstance(value, kind):
            raise TypeError(f"{agent}'s {name} must be of type {kind.__name__}, got "
                            f"{type(value).__name__}")


def _fields_differing(state: TrainState, expected: TrainState, most: int = 4) -> str:
    """The fields of `state` that `expected` lacks and those it lacks of `expected`, or "" if
    they hold the same fields; their couplings left out (a state's own, or none: the
    configuration's)."""
    def paths(tree):
        leaves = jax.tree_util.tree_leaves_with_path(tree.replace(couplings=None))
        return {jax.tree_util.keystr(path) for path, _ in leaves}
    extra, missing = sorted(paths(state) - paths(expected)), sorted(paths(expected) - paths(state))
    if not extra and not missing:
        return ""
    return f"fields not this agent's {extra[:most]}, this agent's fields missing {missing[:most]}"


def _shapes_differing(state: TrainState, expected: TrainState, most: int = 4) -> list[str]:
    """Where `state` (or a batch of states, leading dims those of its `generation`), with the
    fields of `expected`, differs from it in a leaf's shape, one line per leaf, `most` at the
    most. PRNG keys are left out: a state holds raw or typed keys alike; so are its couplings."""
    found = jax.tree.leaves(state.replace(couplings=None))
    wanted = jax.tree_util.tree_leaves_with_path(expected.replace(couplings=None))
    batch = tuple(jnp.shape(state.generation))
    differ = [f"{jax.tree_util.keystr(path)} {tuple(jnp.shape(x))[len(batch):]} (this agent: "
              f"{want.shape})"
              for x, (path, want) in zip(found, wanted)
              if not _is_key(want) and tuple(jnp.shape(x)) != batch + want.shape]
    return differ[:most] + ([f"and {len(differ) - most} more"] if len(differ) > most else [])


def _is_key(leaf: jax.ShapeDtypeStruct) -> bool:
    return leaf.dtype == jnp.uint32 or jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)

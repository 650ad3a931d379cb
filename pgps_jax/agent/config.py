"""PGPSConfig: every hyper-parameter of the paper (Tables 2-4) plus per-task presets; and
EvaluationConfig, the settings of the test evaluation (Section 5.1).

The configuration is static: it fixes array shapes and loop structure, so it is bound when the
algorithm's functions are built and never lives inside the TrainState.
"""

import dataclasses
import math
import numbers
from typing import Tuple

import numpy as np

TASK_NAMES = ("swimmer", "halfcheetah", "hopper", "walker2d", "ant")
FELL_BEHIND_RULES = ("mean_minus_std", "mean")
BETA_ADAPTED = ("before_block", "after_block")
ALGORITHMS = ("pgps", "cem", "td3", "cemrl")
"""PGPS and the baselines built from its parts (`pgps_jax.agent.algorithms`)."""

VALUES_BEFORE_ADDED = {"resample_before_q_filter": True, "fell_behind_rule": "mean_minus_std"}
"""The values that runs saved before these PGPSConfig fields existed ran under, where that is
not the field's default (the population was sampled every generation, the TD3 actor guided
below mean − std). Every other field a saved run lacks counts as having run at its default
(`values_before_added`), so a field added later whose default is not the behaviour from
before it must be listed here."""

@dataclasses.dataclass(frozen=True)
class PGPSConfig:
    """Hyper-parameters of PGPS. Defaults are Table 3, and in two of the four places where
    the paper's text and the authors' code differ the latter (`resample_before_q_filter`,
    `fell_behind_rule`; `beta_adapted` and `target_actor_from_elite` follow Algorithms 1 and
    3); `for_task` applies Table 4."""

    # --- CEM (Section 3, Table 3/4) ---
    pop_size: int = 10
    """N: actors evaluated per generation."""
    top_k: int = 5
    """K: actors whose parameters update the search distribution."""
    sigma_init: float = 7.5e-3
    """Σ_init: initial variance and initial additive damping of the diagonal CEM."""
    sigma_limit: float = 1e-5
    """Σ_limit: value the additive damping decays toward."""
    sigma_decay: float = 0.03
    """τ_Σ: damping ← (1 − τ_Σ)·damping + τ_Σ·Σ_limit each generation."""
    cem_divide_by_k: bool = True
    """Divide the weighted variance term by K, as the authors' (CEM-RL derived) code does."""
    elitism: bool = True
    """The last generation's elite plays again in slot 0 (Algorithm 1; off in CEM-RL), once
    the population is sampled (with `keeps_population`, from the start of Q-filtering)."""

    # --- networks (Table 2) ---
    actor_hidden: Tuple[int, ...] = (400, 300)
    """Hidden layer widths of the actor (ELU, tanh output)."""
    critic_hidden: Tuple[int, ...] = (400, 300)
    """Hidden layer widths of each of the twin critics (ELU, linear output)."""

    # --- TD3 (Table 3, Appendix B) ---
    actor_lr: float = 2e-3
    """Adam learning rate of the TD3 actor."""
    critic_lr: float = 1e-3
    """Adam learning rate of the twin critics."""
    tau: float = 0.005
    """Soft target update rate: target ← τ·online + (1 − τ)·target."""
    gamma: float = 0.99
    """Discount factor."""
    batch_size: int = 256
    """κ: mini-batch size of every TD3 update."""
    policy_noise: float = 0.2
    """Std of the target policy smoothing noise."""
    noise_clip: float = 0.5
    """Clip of the target policy smoothing noise."""
    weight_decay: float = 1e-5
    """L2 weight decay added to the gradients (authors' code)."""
    max_grad_norm: float = 10.0
    """Global gradient-norm clip (authors' code); 0: no clipping."""
    update_blocks: int = 5
    """Blocks per generation: each is num_update critic then num_update actor updates."""
    update_unroll: int = 4
    """Updates per trip of the update loops (speed only; results are the same)."""

    policy_delay: int = 2
    """d: the TD3 baseline trains the actor and moves the targets every d critic updates
    (Fujimoto et al., 2018); PGPS's block schedule (Appendix B) has no delay."""
    exploration_noise: float = 0.1
    """Std of the Gaussian noise on the TD3 baseline's actions while it collects experience
    (Fujimoto et al., 2018); PGPS's actors explore through the CEM's sampling instead."""
    exploring_episodes: int = 1
    """Episodes the TD3 baseline plays side by side per generation, each with its own noise,
    before its updates (one per step of all of them). Fujimoto et al. play one; k of them
    cut the sequential env steps of a run k-fold, the data being up to k episodes older."""

    # --- replay buffer and warm-up ---
    buffer_size: int = 1_000_000
    """Replay buffer capacity (Table 3)."""
    warmup_steps: int = 10_000
    """Uniform-random-action steps that fill the buffer before generation 1 (counted)."""

    # --- mutual guidance (Section 4) ---
    td3_to_cem_period: int = 1
    """F_TD3→CEM: the TD3 actor replaces the last actor every F generations."""
    beta_init: float = 1.0
    """β_init: initial distance weight of the augmented loss (eq. 2)."""
    beta_min: float = 1e-3
    """Lower clamp of β."""
    beta_max: float = 1024.0
    """Upper clamp of β."""
    d_target: float = 0.05
    """D_target of the β rule (eq. 3)."""
    ss2_size: int = 512
    """SS_2: states drawn to measure D in each guided block."""
    beta_adapted: str = "before_block"
    """When a guided block adapts β (eq. 3): "before_block", from D before its updates
    (Algorithm 1); "after_block", from D after its updates on the same SS_2 states, the new β
    weighting the next block (what the authors' code does)."""
    fell_behind_rule: str = "mean"
    """When the TD3 actor fell behind (EA→PG): "mean", Return_TD3 < mean of the generation's
    returns (what the authors' code computes: its std is taken of a single return);
    "mean_minus_std", Return_TD3 < mean − std (Algorithm 1)."""
    target_actor_from_elite: bool = False
    """False: the TD3 target actor π' follows the TD3 actor alone (τ), as in Algorithm 3.
    True: set it to the elite before each generation's updates, as the authors' code does
    whatever its switches ("the critic is trained through the target actor indirectly guided
    by the elite actor", Section 4.2)."""

    # --- Q-critic filtering (Algorithm 2) ---
    q_filter_start: int = 150_000
    """T_start-Q: total steps after which half the population is chosen by the critic."""
    sample_ratio: float = 50
    """SR: M = ⌊SR·N⌋ candidates are scored by the critic."""
    ss1_size: int = 64
    """SS_1: states on which each candidate's Q is averaged."""
    resample_before_q_filter: bool = False
    """True: sample the population from N(μ, Σ) every generation from the first (the text of
    Algorithm 1). False (what the authors' code runs, and the paper's results come from): keep
    the population drawn at the start (μ and N−1 samples; the TD3 actor takes slot N−1 on its
    turns) until Q-filtering starts, while μ and Σ still update. Without Q-filtering it has no
    effect: the population is sampled every generation, as in the authors' code."""

    # --- increasing evaluation steps (eq. 4) ---
    t_init: int = 400
    """T_init: episode length cap at the start."""
    t_max: int = 1000
    """T_max: final episode length cap (also the task's time limit)."""
    t_interval: int = 100_000
    """T_interval: total steps between increases."""
    t_increment: int = 100
    """Steps added to T every T_interval total steps."""

    # --- ablations (Table 1); all False gives the Base model ---
    pg_guides_ea: bool = True
    """PG→EA: inject the TD3 actor into the population."""
    ea_guides_pg: bool = True
    """EA→PG: train a lagging TD3 actor with the augmented loss L^A."""
    q_filter: bool = True
    """Q-critic filtering of sampled actors."""
    increasing_steps: bool = True
    """Increasing evaluation steps (eq. 4); when off, T = T_max."""

    def __post_init__(self):
        _check_types(self)
        _validate(self)

    @property
    def num_elite_filtered(self) -> int:
        """Population slots [N/2, N) that Q-critic filtering fills."""
        return self.pop_size - self.pop_size // 2

    @property
    def keeps_population(self) -> bool:
        """Whether the population drawn at the start is kept until Q-filtering starts
        (`resample_before_q_filter` off, with Q-filtering on)."""
        return self.q_filter and not self.resample_before_q_filter

    @property
    def warmup_steps_per_env(self) -> int:
        """Steps of each of the warm-up's `pop_size` envs side by side: ⌈warmup_steps / N⌉
        (the warm-up writes N times as many rows)."""
        return -(-self.warmup_steps // self.pop_size)

    @property
    def num_candidates(self) -> int:
        """M = ⌊SR·N⌋ candidates scored by the critic (Algorithm 2)."""
        return int(self.sample_ratio * self.pop_size)

    @property
    def td3_probe(self) -> bool:
        """Whether the TD3 actor runs in an extra slot outside the population.

        Without PG→EA the TD3 actor is never in the population, yet EA→PG needs its return to
        decide whether it fell behind; it then gets an extra episode that the CEM ignores.
        """
        return self.ea_guides_pg and not self.pg_guides_ea

    def replace(self, **changes) -> "PGPSConfig":
        """A copy with `changes` applied (validated)."""
        return dataclasses.replace(self, **changes)


# Table 4 (and the τ_Σ values of the authors' code), keyed by task; on swimmer also the
# authors' code's T_init and D_target, where they differ from Table 3.
_TASK_PRESETS = {
    "swimmer": dict(pop_size=10, top_k=5, td3_to_cem_period=3, sigma_decay=0.01, t_init=500,
                    d_target=0.03),
    "halfcheetah": dict(pop_size=10, top_k=5, td3_to_cem_period=1, sigma_decay=0.03),
    "hopper": dict(pop_size=6, top_k=3, td3_to_cem_period=1, sigma_decay=0.03),
    "walker2d": dict(pop_size=6, top_k=3, td3_to_cem_period=1, sigma_decay=0.03),
    "ant": dict(pop_size=6, top_k=3, td3_to_cem_period=1, sigma_decay=0.03),
}


# The baselines' published hyper-parameters where they differ from PGPS's (Table 3), on every
# task; `configs/algo/<name>.yaml` holds the same values. CEM and CEM-RL: Pourchot & Sigaud
# (2019), whose CEM the paper's is (damping 1e-3 decaying by 0.95 a generation, no elitism);
# TD3: Fujimoto et al. (2018), Table 3 and its published code.
_ALGORITHM_PRESETS = {
    "pgps": {},
    "cem": dict(pop_size=10, top_k=5, sigma_init=1e-3, sigma_decay=0.05, elitism=False,
                warmup_steps=0, increasing_steps=False, q_filter=False, pg_guides_ea=False,
                ea_guides_pg=False),
    "td3": dict(actor_lr=1e-3, critic_lr=1e-3, batch_size=100, weight_decay=0.0,
                max_grad_norm=0.0, policy_delay=2, exploration_noise=0.1,
                increasing_steps=False, q_filter=False, pg_guides_ea=False, ea_guides_pg=False),
    "cemrl": dict(pop_size=10, top_k=5, sigma_init=1e-3, sigma_decay=0.05, elitism=False,
                  actor_lr=1e-3, critic_lr=1e-3, batch_size=100, weight_decay=0.0,
                  max_grad_norm=0.0, increasing_steps=False, q_filter=False,
                  pg_guides_ea=False, ea_guides_pg=False),
}


def for_task(task: str, algo: str = "pgps", **overrides) -> PGPSConfig:
    """The configuration of `algo` on `task`, with `overrides` applied: for PGPS the paper's
    (Tables 3 and 4, with the authors' code where `PGPSConfig` and `_TASK_PRESETS` say); for a
    baseline its published hyper-parameters on top of those."""
    if task not in _TASK_PRESETS:
        hint = (" (the point mass, a smoke test, has no paper configuration: give PGPSConfig "
                "the sizes of configs/env/point.yaml)" if task == "point" else "")
        raise ValueError(f"unknown task {task!r}; valid tasks: {', '.join(TASK_NAMES)}{hint}")
    return PGPSConfig(**{**_TASK_PRESETS[task], **algorithm_preset(algo), **overrides})


SWITCHES = ("pg_guides_ea", "ea_guides_pg", "q_filter", "increasing_steps")
"""PGPS's four couplings as `PGPSConfig` fields (Table 1's models differ in these alone; a
`Couplings` carries them); the baselines have none of them."""


def recorded_episodes(algo: str, config: "PGPSConfig") -> int:
    """The episodes of one generation of `algo` whose transitions enter the replay buffer:
    PGPS's population (with the TD3 actor's extra episode where it has one), CEM-RL's
    population, TD3 alone's exploring episodes; CEM alone keeps none."""
    algorithm_preset(algo)
    return {"pgps": config.pop_size + int(config.td3_probe), "cemrl": config.pop_size,
            "td3": config.exploring_episodes, "cem": 0}[algo]


def check_for_algorithm(algo: str, config: "PGPSConfig") -> None:
    """Raises ValueError naming a field whose value `algo` cannot run with (CEM alone has no
    replay buffer to warm up; a buffer holds at least one generation's transitions)."""
    algorithm_preset(algo)
    if algo == "cem" and config.warmup_steps:
        raise ValueError(f"CEM alone has no replay buffer to warm up: warmup_steps must be 0, "
                         f"got {config.warmup_steps}")
    episodes = recorded_episodes(algo, config)
    _require(episodes * config.t_max <= config.buffer_size, "buffer_size", config.buffer_size,
             f">= {episodes} episodes × t_max = {episodes * config.t_max} (one generation's "
             f"transitions for {algo})")


def algorithm_preset(algo: str) -> dict:
    """The fields in which `algo`'s hyper-parameters differ from PGPS's; ValueError naming
    the algorithms for an unknown one."""
    if algo not in _ALGORITHM_PRESETS:
        raise ValueError(f"unknown algorithm {algo!r}; valid: {', '.join(ALGORITHMS)}")
    return dict(_ALGORITHM_PRESETS[algo])


@dataclasses.dataclass(frozen=True)
class EvaluationConfig:
    """When and how long the test episodes run (Section 5.1)."""

    every: int = 10_000
    """Env steps between evaluations: one falls due at each multiple. A generation that plays
    more than `every` steps crosses several at once and begins one evaluation for them (its
    actors are the same for all of them)."""
    episodes: int = 10
    """Test episodes per actor."""
    steps: int = 1000
    """Step limit of a test episode."""

    def __post_init__(self):
        _check_types(self)
        for name in ("every", "episodes", "steps"):
            value = getattr(self, name)
            if value <= 0:
                raise ValueError(f"EvaluationConfig.{name}={value!r} is invalid: must be a "
                                 "positive integer")


INERT_WITHOUT = {
    "q_filter": ("resample_before_q_filter",),
    "ea_guides_pg": ("fell_behind_rule", "beta_min", "beta_max", "d_target", "ss2_size",
                     "beta_adapted"),
    "increasing_steps": ("t_init", "t_interval", "t_increment"),
}
"""The settings that act only through a coupling, by the coupling's field."""


def effective_fields(fields: dict) -> dict:
    """A PGPSConfig's fields (as `dataclasses.asdict` gives them) less those that cannot act
    under the others' values, so that two configurations running the same algorithm compare
    equal: a coupling's settings (`INERT_WITHOUT`) where it is off."""
    dropped = {name for switch, names in INERT_WITHOUT.items() if not fields.get(switch, True)
               for name in names}
    return {name: value for name, value in fields.items() if name not in dropped}


def values_before_added() -> dict:
    """Per PGPSConfig field, what a run saved before the field existed ran under: its default,
    or its value then where that differs (`VALUES_BEFORE_ADDED`); tuples as lists, as saved."""
    values = {}
    for f in dataclasses.fields(PGPSConfig):
        value = VALUES_BEFORE_ADDED.get(f.name, f.default)
        values[f.name] = list(value) if isinstance(value, tuple) else value
    return values


def saved_fields_as_run(saved: dict) -> dict:
    """The fields of a PGPSConfig saved by an earlier version as its run ran them: those it
    lacks at `values_before_added`, then `effective_fields` (its own fields keep their
    order)."""
    fields = dict(saved)
    for name, value in values_before_added().items():
        fields.setdefault(name, value)
    return effective_fields(fields)


def _is_integer(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def _check_types(config) -> None:
    """Raise ValueError naming a field whose value is not of its annotated type (a bool for a
    switch, an integer for a count, a finite number, a string, a tuple of integer widths);
    numpy scalars are stored as Python ones and widths as a tuple."""
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if field.type is bool:
            ok, valid = isinstance(value, (bool, np.bool_)), "True or False"
            plain = bool(value) if ok else value
        elif field.type is int:
            ok, valid = _is_integer(value), "an integer"
            plain = int(value) if ok else value
        elif field.type is float:
            ok = (isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
                  and math.isfinite(value))
            valid = "a finite number"
            plain = value if type(value) in (int, float) or not ok else float(value)
        elif field.type is str:
            ok, valid, plain = isinstance(value, str), "a string", value
        elif field.type == Tuple[int, ...]:  # layer widths
            ok = isinstance(value, (tuple, list)) and all(_is_integer(w) for w in value)
            valid = "a tuple of integer layer widths"
            plain = tuple(int(w) for w in value) if ok else value
        else:
            raise TypeError(f"{type(config).__name__}.{field.name}: no type check for "
                            f"{field.type}")
        if not ok:
            raise ValueError(f"{type(config).__name__}.{field.name}={value!r} is invalid: "
                             f"must be {valid}")
        object.__setattr__(config, field.name, plain)


def _require(ok: bool, field: str, value, valid: str) -> None:
    if not ok:
        raise ValueError(f"PGPSConfig.{field}={value!r} is invalid: must be {valid}")


def _validate(c: PGPSConfig) -> None:
    """Raise ValueError naming the field, its value and the valid range."""
    _require(c.pop_size >= 2, "pop_size", c.pop_size, "an integer >= 2")
    _require(1 <= c.top_k <= c.pop_size, "top_k", c.top_k, f"in [1, pop_size={c.pop_size}]")
    positive_ints = ("batch_size", "buffer_size", "update_blocks", "update_unroll",
                     "td3_to_cem_period", "policy_delay", "exploring_episodes",
                     "ss1_size", "ss2_size", "t_init", "t_max", "t_interval")
    for name in positive_ints:
        value = getattr(c, name)
        _require(value > 0, name, value, "a positive integer")
    for name in ("warmup_steps", "q_filter_start", "t_increment"):
        value = getattr(c, name)
        _require(value >= 0, name, value, "a non-negative integer")
    positive_floats = ("sigma_init", "sigma_limit", "actor_lr", "critic_lr", "beta_init",
                       "beta_min", "beta_max", "d_target", "sample_ratio")
    for name in positive_floats:
        value = getattr(c, name)
        _require(value > 0, name, value, "> 0")
    for name in ("tau", "sigma_decay"):
        value = getattr(c, name)
        _require(0 < value <= 1, name, value, "in (0, 1]")
    _require(0 <= c.gamma < 1, "gamma", c.gamma, "in [0, 1)")
    for name in ("policy_noise", "noise_clip", "weight_decay", "max_grad_norm",
                 "exploration_noise"):
        _require(getattr(c, name) >= 0, name, getattr(c, name), ">= 0")
    _require(c.beta_min <= c.beta_init <= c.beta_max, "beta_init", c.beta_init,
             f"in [beta_min={c.beta_min}, beta_max={c.beta_max}]")
    _require(c.fell_behind_rule in FELL_BEHIND_RULES, "fell_behind_rule", c.fell_behind_rule,
             f"one of {', '.join(FELL_BEHIND_RULES)}")
    _require(c.beta_adapted in BETA_ADAPTED, "beta_adapted", c.beta_adapted,
             f"one of {', '.join(BETA_ADAPTED)}")
    _require(c.t_init <= c.t_max, "t_init", c.t_init, f"<= t_max={c.t_max}")
    _require(c.num_candidates >= c.num_elite_filtered, "sample_ratio", c.sample_ratio,
             f"large enough that SR·N = {c.num_candidates} candidates >= the "
             f"{c.num_elite_filtered} population slots Q-filtering fills")
    _require(c.buffer_size < 2**31, "buffer_size", c.buffer_size,
             "< 2**31 (the buffer's rows are counted in int32)")
    for name in ("batch_size", "ss1_size", "ss2_size"):  # samples of the buffer's rows
        value = getattr(c, name)
        _require(value <= c.buffer_size, name, value, f"<= buffer_size={c.buffer_size} (a "
                 "sample of the buffer's rows)")
    warmup_rows = c.warmup_steps_per_env * c.pop_size
    _require(warmup_rows <= c.buffer_size, "warmup_steps", c.warmup_steps,
             f"at most buffer_size={c.buffer_size} once rounded up to a multiple of "
             f"pop_size={c.pop_size} (the warm-up's envs side by side): {warmup_rows} rows")
    for name in ("actor_hidden", "critic_hidden"):
        widths = getattr(c, name)
        _require(len(widths) > 0 and all(w > 0 for w in widths), name, widths,
                 "a non-empty tuple of positive layer widths")

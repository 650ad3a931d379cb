"""What a generation reports: every metric's name, meaning and when it holds a value.

An algorithm's `learn` returns a flat dict with exactly the keys of its
`generation_metrics()` (PGPS: `generation_metrics(N)`; the baselines: a `chosen` few),
`EVALUATION_REPORT`, `evaluation_metrics(actors)` and `returns_key(actor)` for each actor it
evaluates; the run's writers (metrics.csv, eval_policies.csv, TensorBoard) take their
columns and tags from these tables.

Per generation: every `generation_metrics` entry; one whose `defined_by` names a boolean
metric holds NaN in the generations where that is false (the TD3 actor's return when it did
not play). Per evaluation: `eval/done` says whether a test evaluation ended in this
generation; only then do `eval/step` and the `evaluation_metrics` entries hold its results.
"""

import dataclasses
from typing import Optional


@dataclasses.dataclass(frozen=True)
class Metric:
    key: str
    """Its key in the metrics dict."""
    column: str
    """Its column in the run's CSV."""
    meaning: str
    defined_by: Optional[str] = None
    """A boolean metric; this one holds a value only where that is true (NaN otherwise)."""


_HEAD = (
    Metric("gen/generation", "generation", "generations completed"),
    Metric("gen/total_steps", "env_steps", "env steps so far, the random warm-up included"),
    Metric("gen/episode_limit", "T", "step limit T of this generation's episodes (eq. 4)"),
    Metric("gen/interaction_steps", "interaction_steps",
           "env steps the generation's episodes took (the TD3 updates that follow)"),
    Metric("gen/rollout_steps", "rollout_steps",
           "sequential env steps of the generation's rollout: its longest episode, or the test "
           "episodes it had to finish (the rollout's cost; seeds vmapped all wait for the most)"),
)
_TAIL = (
    Metric("pop/return_mean", "return_mean", "mean return of the population"),
    Metric("pop/return_std", "return_std", "std of the population's returns"),
    Metric("cem/elite_return", "elite_return", "best return of the generation (the new elite)"),
    Metric("td3/return", "td3_return",
           "return of the TD3 actor's episode (TD3 alone: the mean of its episodes)",
           defined_by="td3/in_population"),
    Metric("td3/in_population", "td3_in_population",
           "the TD3 actor played an episode this generation (PG→EA, or the probe slot)"),
    Metric("td3/guided_loss", "guided_loss",
           "the TD3 actor fell behind and trained on the augmented loss L^A (EA→PG, eq. 2)"),
    Metric("td3/beta", "beta", "distance weight β of L^A after this generation (eq. 3)"),
    Metric("td3/critic_loss", "critic_loss", "mean critic loss of the generation's updates"),
    Metric("td3/actor_loss", "actor_loss", "mean actor loss of the generation's updates"),
    Metric("cem/var_mean", "cem_var_mean", "mean of the CEM's diagonal variance Σ"),
    Metric("cem/damping", "cem_damping", "additive damping of Σ"),
    Metric("gen/q_filter_active", "q_filter_active",
           "half the population was chosen by the critic (Algorithm 2)"),
    Metric("pop/unstable_episodes", "unstable_episodes",
           "episodes ended by non-finite physics (their last step is not stored)"),
)


def population_return_key(i: int) -> str:
    return f"pop/return_{i}"


def generation_metrics(pop_size: int) -> tuple[Metric, ...]:
    """The per-generation metrics of a population of `pop_size`, in metrics.csv's order."""
    returns = tuple(Metric(population_return_key(i), f"return_{i}", f"return of actor {i}")
                    for i in range(pop_size))
    return _HEAD + returns + _TAIL


def chosen(keys: tuple[str, ...], pop_size: int) -> tuple[Metric, ...]:
    """The metrics of `keys`, in that order (an algorithm reporting a part of PGPS's)."""
    catalogue = {m.key: m for m in generation_metrics(pop_size)}
    return tuple(catalogue[key] for key in keys)


EVALUATION_REPORT = (
    Metric("eval/done", "done", "a test evaluation ended in this generation"),
    Metric("eval/step", "Step", "env steps when the evaluation began (its actors' state)",
           defined_by="eval/done"),
)


def evaluation_metrics(actors: tuple[str, ...]) -> tuple[Metric, ...]:
    """Mean and std of the test returns of each of `actors` (Section 5.1)."""
    return tuple(Metric(f"eval/{actor}_{stat}", f"{actor}_{stat}",
                        f"{stat} of the {actor} actor's test returns", defined_by="eval/done")
                 for actor in actors for stat in ("mean", "std"))


def returns_key(actor: str) -> str:
    """The key of `actor`'s test returns [E] (an agent's `evaluated`)."""
    return f"eval/{actor}_returns"


def holds_value(key: str, metrics: dict) -> bool:
    """Whether the metric `key` holds a value in this generation's `metrics` (host values)."""
    if key.startswith("eval/") and key != "eval/done":
        condition = "eval/done"
    else:
        condition = next((m.defined_by for m in _TAIL if m.key == key), None)
    return condition is None or bool(metrics.get(condition, True))

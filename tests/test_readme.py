"""The README's "Using the algorithm from JAX" snippets run as written, one after the other,
on the point mass with a tiny configuration in place of hopper's (the API is what they
check)."""

import pathlib
import re

import pgps_jax.agent.config
import pgps_jax.agent.pgps  # loaded before the patches below: its defaults call EvaluationConfig
import pgps_jax.envs
from pgps_jax.envs.point import PointMass

README = pathlib.Path(__file__).resolve().parent.parent / "README.md"


def _snippets() -> str:
    section = README.read_text().split("## Using the algorithm from JAX", 1)[1]
    section = section.split("\n## ", 1)[0]
    return "\n".join(re.findall(r"```python\n(.*?)```", section, re.S))


def test_the_readme_snippet_runs(monkeypatch, capsys, tmp_path):
    tiny = pgps_jax.agent.config.PGPSConfig(
        pop_size=2, top_k=1, actor_hidden=(8,), critic_hidden=(8,), buffer_size=400,
        warmup_steps=40, t_init=10, t_max=20, t_interval=100, batch_size=8, ss1_size=4,
        ss2_size=8, sample_ratio=2, q_filter_start=60)
    tiny_tests = pgps_jax.agent.config.EvaluationConfig(every=40, episodes=2, steps=15)
    asked = []
    monkeypatch.setattr(pgps_jax.agent.config, "for_task",
                        lambda task, **overrides: asked.append(task) or tiny.replace(**overrides))
    monkeypatch.setattr(pgps_jax.agent.config, "EvaluationConfig",
                        lambda **settings: asked.append(settings) or tiny_tests)
    monkeypatch.setattr(pgps_jax.envs, "make_env", lambda task: asked.append(task) or PointMass())
    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(compile(_snippets(), str(README), "exec"), namespace)
    assert asked == [dict(every=10_000, episodes=10, steps=1000), "hopper", "hopper",
                     "hopper", "hopper"]
    printed = capsys.readouterr().out.split("\n")
    assert len(printed) >= 3  # evaluations that ended, then the final one
    assert int(namespace["state"].generation) == 10 == namespace["generation"]
    assert namespace["meta"]["note"] == "any JSON"
    assert (tmp_path / "runs/mine/checkpoints/10").is_dir()
    assert namespace["states"].generation.shape == (5,)
    assert namespace["metrics"]["td3/critic_loss"].shape == (5,)
    pair = namespace["pair"]  # Base and PGPS, one state each
    assert pair.generation.shape == (2,)
    assert pair.couplings.q_filter.tolist() == [False, True]

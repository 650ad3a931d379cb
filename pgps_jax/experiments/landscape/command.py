"""`python -m pgps_jax.landscape`: train or load, sweep, write; its command line."""

import csv
import dataclasses
import logging
import pathlib
import sys
import time
import typing
from typing import Callable, Optional, Sequence, Union

import jax
import jax.numpy as jnp

from pgps_jax.envs import Env
from pgps_jax.cli.errors import EXIT_OK, UsageError, report
from pgps_jax.cli.run_config import CONFIG_DIR, coerce, parse_overrides
from pgps_jax.experiments.landscape.config import SweepConfig, TrainConfig, resolve_params
from pgps_jax.experiments.landscape.output import (ANALYSIS_COLUMNS, format_analysis,
                                                   param_label, plot_landscape,
                                                   write_sweep_csv)
from pgps_jax.experiments.landscape.search import (TrainResult, load_theta, save_theta,
                                                   train_linear_policy)
from pgps_jax.experiments.landscape.sweep import analyse_curve, make_sweep, sweep_values


def run(env: Env, env_name: str, train_config: TrainConfig, sweep_config: SweepConfig,
        out_dir: Union[str, pathlib.Path], key: jax.Array, params: Optional[Sequence] = None,
        params_file: Optional[str] = None, log: Callable[[str], None] = print) -> list[dict]:
    """(host) Appendix A end to end; returns the analysis rows (also in analysis.csv).

    Writes to `out_dir`: theta.npz (trained or loaded W), sweep_<row>_<col>.csv per parameter,
    landscape.png and analysis.csv.
    """
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    shape = (env.observation_size, env.action_size)
    indices = resolve_params(params, shape, sweep_config.num_params)
    train_key, sweep_key = jax.random.split(key)
    start = time.perf_counter()
    if params_file:
        theta = load_theta(params_file, shape)
        result = TrainResult(theta=theta, mean_return=float("nan"), generations=0, reached=False)
        log(f"loaded W {shape} from {params_file}")
    else:
        result = train_linear_policy(env, train_config, train_key, log)
        theta = result.theta
        log(f"CEM: average return {result.mean_return:.2f} after {result.generations} "
            f"generations ({time.perf_counter() - start:.1f} s)")
    save_theta(out / "theta.npz", result, env_name)

    sweep = make_sweep(env, sweep_config.steps, sweep_config.gamma)
    reset_keys = jax.random.split(sweep_key, sweep_config.seeds)
    sweeps, labels, rows = [], [], []
    for index in indices:
        tick = time.perf_counter()
        row, col = divmod(index, shape[1])
        center = float(theta.reshape(-1)[index])
        values = sweep_values(center, sweep_config)
        result_i = jax.device_get(sweep(jnp.asarray(theta), jnp.asarray(index, jnp.int32),
                                        jnp.asarray(values), reset_keys))
        write_sweep_csv(out / f"sweep_{row}_{col}.csv", result_i)
        disc = analyse_curve(values, result_i.discounted.mean(axis=1), sweep_config.flat_tol,
                             sweep_config.flat_atol)
        ret = analyse_curve(values, result_i.returns.mean(axis=1), sweep_config.flat_tol,
                            sweep_config.flat_atol)
        label = param_label(index, shape)
        rows.append({"parameter": label, "row": row, "col": col, "trained_value": center,
                     "flat_fraction": disc["flat_fraction"],
                     "max_jump_discounted": disc["max_jump"], "max_jump_at": disc["max_jump_at"],
                     "max_jump_relative": disc["max_jump_relative"],
                     "max_jump_return": ret["max_jump"], "discounted_range": disc["range"],
                     "return_range": ret["range"]})
        sweeps.append(result_i)
        labels.append(label)
        log(f"swept {label}: {values.size} points x {sweep_config.seeds} seeds in "
            f"{time.perf_counter() - tick:.1f} s")

    with open(out / "analysis.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=ANALYSIS_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    trained_note = ("loaded" if params_file else
                    f"CEM return {result.mean_return:.0f}" + ("" if result.reached else
                                                              ", threshold not reached"))
    plot_landscape(out / "landscape.png", sweeps, labels,
                   [float(theta.reshape(-1)[i]) for i in indices],
                   f"{env_name}: linear tanh policy ({trained_note}); mean ± std over "
                   f"{sweep_config.seeds} seeds, γ={sweep_config.gamma}, "
                   f"{sweep_config.steps} steps")
    log(f"analysis (discounted return J; flat = |dJ/dθ| ≤ {sweep_config.flat_tol} · "
        "range(J)/range(θ)):\n" + format_analysis(rows))
    log(f"wrote {out} ({time.perf_counter() - start:.1f} s in all)")
    return rows


_SECTIONS = {"cem": TrainConfig, "sweep": SweepConfig}
_TOP = {"seed": int, "threshold": float, "params_file": str, "steps": int, "gamma": float,
        "output_dir": str}


def _fields(section: str) -> list[str]:
    return [f.name for f in dataclasses.fields(_SECTIONS[section])
            if f.name not in ("steps", "threshold")]


def _valid_settings_text() -> str:
    return ("valid settings: env=<task>, " + ", ".join(_TOP) + ", "
            + ", ".join(f"{s}.{f}" for s in _SECTIONS for f in _fields(s)))


def check_overrides(args: Sequence[str]) -> None:
    """Checks the command line before Hydra composes it: unknown keys and tasks."""
    from pgps_jax.envs import TASKS
    for o in parse_overrides(args):
        key = o.key_or_group
        if key.startswith("hydra"):
            continue
        if key == "env":
            if o.value() not in TASKS:
                raise UsageError(f"unknown env {o.value()!r}; choices: {', '.join(TASKS)}")
            continue
        section, _, field = key.partition(".")
        if key in _TOP or (section in _SECTIONS and field in _fields(section)):
            continue
        raise UsageError(f"unknown setting {key!r}; {_valid_settings_text()}")


def configs_from_dict(cfg: dict) -> tuple[TrainConfig, SweepConfig]:
    """Validated dataclasses from the `configs/landscape.yaml` layout (a plain dict); a
    UsageError names a value of the wrong type or out of range."""
    steps, gamma = coerce("steps", cfg["steps"], int), coerce("gamma", cfg["gamma"], float)
    threshold = coerce("threshold", cfg["threshold"], float)
    kwargs = {}
    for section, kind in _SECTIONS.items():
        hints = typing.get_type_hints(kind)
        given = cfg.get(section) or {}
        kwargs[section] = {k: v if k == "params" else coerce(f"{section}.{k}", v, hints[k])
                           for k, v in given.items() if k in _fields(section)}
    train = TrainConfig(threshold=threshold, steps=steps, **kwargs["cem"])
    sweep = SweepConfig(steps=steps, gamma=gamma,
                        **{k: v for k, v in kwargs["sweep"].items() if k != "params"})
    return train, sweep


def _main(cfg) -> None:
    """Hydra entry: `python -m pgps_jax.landscape env=swimmer`."""
    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf
    from pgps_jax.envs import make_env

    def body() -> int:
        logging.getLogger("jax").setLevel(logging.WARNING)  # Hydra logs INFO: not JAX's
        plain = OmegaConf.to_container(cfg, resolve=True)
        train, sweep = configs_from_dict(plain)
        name = HydraConfig.get().runtime.choices["env"]
        out_dir = plain.get("output_dir") or HydraConfig.get().runtime.output_dir
        params_file = plain.get("params_file")
        if params_file:
            params_file = hydra.utils.to_absolute_path(params_file)
            if not pathlib.Path(params_file).is_file():
                raise UsageError(f"params_file={plain['params_file']}: no such file")
        run(make_env(name), name, train, sweep, out_dir,
            jax.random.PRNGKey(coerce("seed", plain["seed"], int)),
            params=plain.get("sweep", {}).get("params"), params_file=params_file,
            log=logging.getLogger(__name__).info)
        return EXIT_OK

    code = report(body)
    if code != EXIT_OK:
        sys.exit(code)


def main() -> None:
    """Checks the command line, then runs `_main` under Hydra (configs/landscape.yaml)."""
    import hydra
    code = report(lambda: check_overrides(sys.argv[1:]) or EXIT_OK)
    if code != EXIT_OK:
        sys.exit(code)
    hydra.main(config_path=str(CONFIG_DIR), config_name="landscape", version_base=None)(_main)()

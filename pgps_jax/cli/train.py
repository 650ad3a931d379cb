"""`python -m pgps_jax.train env=halfcheetah`: train PGPS on a task, with logs and checkpoints.

    python -m pgps_jax.train env=hopper seed=3 total_steps=200000 pgps.q_filter=false
    python -m pgps_jax.train env=hopper seed=3 resume=true        # continue that run
    python -m pgps_jax.train resume=runs/hopper/seed3             # the same, by directory

Hydra composes `configs/config.yaml` with `configs/env/<task>.yaml` and the command line; the
result is turned once into `RunSettings` and the frozen `PGPSConfig`
(`pgps_jax.cli.run_config`). `pgps_jax.cli.plan` then decides, before anything is trained or
written, between a new run and a resumed one; `pgps_jax.cli.trainer` runs the loop. The heavy
modules (JAX, orbax) are imported only once the command line is known to be good, so a
mistake is reported at once.

Exit status: 0 done, 1 the run failed (a non-finite metric), 2 a bad setting or command line
(nothing was trained or written), 130 stopped by SIGINT/SIGTERM after writing a checkpoint.
"""

import sys
from typing import Any, Mapping, Sequence

import hydra
from omegaconf import DictConfig, OmegaConf

from pgps_jax.cli.errors import EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, print_error, report
from pgps_jax.cli.plan import plan
from pgps_jax.cli.run_config import CONFIG_DIR, check_overrides, register_structured_configs
from pgps_jax.cli.stop_request import sigterm_as_ctrl_c


def run(values: Mapping[str, Any], overrides: Sequence[str] = ()) -> int:
    """Plans and trains from a resolved configuration dict; returns the exit status."""
    def body() -> int:
        p = plan(values, overrides)
        from pgps_jax.cli import trainer
        try:
            outcome = trainer.train(p)
        finally:
            p.lock.release()
        return EXIT_OK if outcome == "done" else EXIT_INTERRUPTED

    try:
        with sigterm_as_ctrl_c():
            return report(body)
    except KeyboardInterrupt:
        print_error("aborted (Ctrl-C or SIGTERM) outside the generations' loop; the "
                    "checkpoints written before are intact")
        return EXIT_INTERRUPTED


register_structured_configs()


@hydra.main(config_path=str(CONFIG_DIR), config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig
    try:
        values = OmegaConf.to_container(cfg, resolve=True)
    except Exception as e:  # an interpolation that cannot be resolved
        print_error(f"cannot resolve the configuration: {e}")
        sys.exit(EXIT_USAGE)
    code = run(values, list(HydraConfig.get().overrides.task))
    if code != EXIT_OK:
        sys.exit(code)


def main() -> None:
    """Console entry: check the overrides (unknown keys and tasks), then let Hydra compose."""
    code = report(lambda: check_overrides(sys.argv[1:]) or EXIT_OK)
    if code != EXIT_OK:
        sys.exit(code)
    _hydra_main()

"""The benchmark suite: run each as `python -m benchmarks.<name>` from the repository root."""

import importlib

importlib.import_module("pgps_jax.envs.quiet_mjx")  # before any benchmark imports mujoco.mjx

"""The commands (`train`, `evaluate`, `render`) and the run infrastructure around the agent:
settings (`run_config`), the run directory and its logs (`run_dir`), checkpoints, the
training loop (`trainer`) and the errors a command reports (`errors`)."""

"""The commands (`train`, `evaluate`, `render`) and the run infrastructure around the agent:
settings (`run_config`, `tool_args`), what an invocation will do (`plan`), the training loop
shared with the benchmarks (`loop`, `compile_ahead`), the CLI's run around it (`trainer`),
the run directory and its logs (`run_dir`), checkpoints, and the errors a command reports
(`errors`)."""

"""The benchmark suite: run each as `python -m benchmarks.<name>` from the repository root."""

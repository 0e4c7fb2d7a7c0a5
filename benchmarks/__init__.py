"""geer's benchmark suite: one module per question, each writing one report beside it (docs/benchmarks.md lists
them with the commands that regenerate them). Run from the repository root: `python -m benchmarks.NAME`."""

"""`python -m geer_ns.compare`: geer-compare without the console script installed."""

from geer_ns.compare.cli import entrypoint

entrypoint()

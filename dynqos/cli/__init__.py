"""The `dynqos` command line: a parser per command group (config, sim, edge and onboard, the
experiment, the tools), each dispatching to the `run` of the role or job it starts. It only parses and
dispatches; what each process does at start and stop is the role's own (common/lifecycle.py)."""

from dynqos.cli.main import main

__all__ = ["main"]

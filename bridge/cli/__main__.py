"""`python -m ambhil.bridge.cli ARGS`: the `ambhil` command (children of `ambhil run` start this way)."""
from ambhil.bridge.cli.main import entry

entry()

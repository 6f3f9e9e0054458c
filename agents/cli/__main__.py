"""``python -m agents.cli``: the same as ``rse``."""

from . import main

main()

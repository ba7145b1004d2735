"""``python -m acquisition.cli``: the command line (the demo starts the daemon so where it is not installed)."""

from acquisition.cli import main

main()

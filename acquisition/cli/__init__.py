"""The ``mirrorgonio`` command line: one program, one subcommand per job.

:mod:`acquisition.cli.app` holds the program and what its commands share; each other module
adds its commands to it. The commands import their work when they run, so that the program
starts in a fraction of a second whatever it is asked.
"""

from acquisition.cli import (  # noqa: F401 - they register their commands
    benchmarks,
    daemon,
    demo,
    photometry,
    process,
    rawfiles,
    reflectance,
    simulate,
    verify,
)
from acquisition.cli.app import app, main

__all__ = ["app", "main"]

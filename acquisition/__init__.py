"""Acquisition: the rig description, the run file, and the daemon that drives the devices.

Importing this package stays light (no web framework): the processing side reads the
rig description and run files through :mod:`acquisition.rig` and the run-file module.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mirrorgonio")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"

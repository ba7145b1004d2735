"""Acquisition: the rig description, the run file, and the daemon that drives the devices.

Importing this package stays light (no web framework): the processing side reads the
rig description and run files through :mod:`acquisition.rig` and the run-file module.
"""

"""Simulated devices that stand in for the real arm and camera, over the real protocols.

The simulated arm is a Modbus TCP server (and a serial peer on a pseudo-terminal) driven
by the real drivers; the simulated camera renders the mirrored ball with its own optics,
written without importing :mod:`processing`, and writes real DNG files. Both share one
:class:`~sim_devices.world.SimWorld`, through which the camera learns where the light is.
"""

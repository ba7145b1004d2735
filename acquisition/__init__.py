"""Acquisition: the daemon that drives the arm and the camera, the command line, the demo
and the benchmarks.

The rig description and the run-file format it writes are contracts on the ground floor
(:mod:`drivers.contracts`), read by the processing and the simulated devices too.
"""

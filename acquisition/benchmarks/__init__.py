"""Benchmarks that use the simulated devices to make their inputs (so they live in acquisition/).

Each module has one ``bench_*`` function returning a JSON-ready dictionary; the command
line (``mirrorgonio bench ...``) prints it.
"""

"""The contracts every package reads: the rig description, the run-file format, the version.

They sit on the ground floor, inside :mod:`drivers` (which imports nothing else of the
project), so that the acquisition, the processing and the simulated devices can all read
them without any import running upwards (the import-linter layers contract in
``pyproject.toml`` checks it):

- :mod:`drivers.contracts.rig`: the rig description (geometry, calibration, schedule),
  loaded from TOML; ``docs/rig.md``.
- :mod:`drivers.contracts.runfile`: the run file (HDF5) the daemon writes and the
  processing reads; ``docs/run-file.md``.
- :mod:`drivers.contracts.version`: the software's version, recorded in every file written.

Each contract carries its own version number (``RIG_SCHEMA_VERSION``, ``RUN_FILE_VERSION``).
"""

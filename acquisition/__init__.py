"""Everything that is not the processing: the daemon at the rig, and the tools around it.

- :mod:`acquisition.daemon`: the FastAPI daemon (REST and the web page), its run engine and
  queue, the catalog of runs and jobs, and the processing worker;
- :mod:`acquisition.cli`: the ``mirrorgonio`` command line;
- :mod:`acquisition.demo`: the whole chain on simulated devices (``mirrorgonio demo``);
- :mod:`acquisition.importer`: run files from raw files shot elsewhere (``mirrorgonio import``);
- :mod:`acquisition.benchmarks`: what ``mirrorgonio bench`` measures.

The rig description and the run-file format the daemon writes are contracts on the ground
floor (:mod:`drivers.contracts`), read by the processing and the simulated devices too.
"""

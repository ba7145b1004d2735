"""The acquisition daemon: what runs at the rig while runs are taken and processed.

- :mod:`~acquisition.daemon.app` and :mod:`~acquisition.daemon.api`: the FastAPI application,
  one router per resource, and the web page (``web/``);
- :mod:`~acquisition.daemon.engine`: the run engine, which takes a run's requests; it owns
  its queue of runs (:mod:`~acquisition.daemon.run_queue`), plans each run once
  (:mod:`~acquisition.daemon.run_preflight`), and starts a thread per run
  (:mod:`~acquisition.daemon.run_thread`) that moves the arm through the schedule and takes a
  bracket at each position; beside it the technician's manual control
  (:mod:`~acquisition.daemon.manual`: test shots, jog, home);
- :mod:`~acquisition.daemon.catalog`: the runs and jobs, in SQLite;
- :mod:`~acquisition.daemon.worker`: the processing worker that takes the catalog's jobs.

The tools around it (the command line, the demo, the importer, the benchmarks) are its
siblings in :mod:`acquisition`; the daemon imports none of them.
"""

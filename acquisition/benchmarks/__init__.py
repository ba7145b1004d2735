"""Benchmarks that use the simulated devices to make their inputs (so they live in acquisition/).

Each benchmark is one ``bench_*`` function returning a JSON-ready dictionary, which the
command line (``mirrorgonio bench NAME``) prints and, with ``--record``, writes into the
generated ``docs/benchmarks.md`` (:mod:`~acquisition.benchmarks.record`).

``render``, ``acquire``
    The simulated camera's rendering of a frame; the daemon's overhead with zero-latency
    devices, next to a plain h5py write.
``hdr`` (and ``hdr_methods``)
    This project's raw HDR merge next to its peers on the same brackets: time and error.
``accuracy`` (and ``scoring``)
    The reference simulation through the whole chain, every fitted source scored against
    the truth; ``scoring`` is how a fit is scored, which ``tolerance`` and the demo share.
``reflectance``
    An object's reflectance under three light models, scored against the truth.
``tolerance`` (and ``description_errors``)
    How exact the rig description must be: one run processed with one number of its
    description wrong at a time.
``speed`` (and ``speed_runs``, ``speed_process``, ``speed_resources``, ``speed_steps``, ``speed_report``)
    How fast the whole chain is at two sensor sizes, against the read floor.
"""

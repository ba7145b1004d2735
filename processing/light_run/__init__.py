"""The offline processing of one run file, step by step, position by position.

Steps (``--steps``, :mod:`processing.steps`): ``hdr`` — merge each position's bracket
(``processing.hdr``) into the results file, an OpenEXR and a PNG per position; ``sources``
— per position, the chief rays, the sources' templates and their unmixing (or cell sums);
then per run the fits, the light model, the IES / LDT / TM-25 files and the report.

Positions stream through a :class:`~processing.parallel.Compute` (a Dask cluster, or this
process): every task opens the run file itself, by path, reads one position and returns
only that position's result; this process writes each result into the results file as it
arrives. A run is never loaded whole, and the memory in use is a few positions' worth
whatever the run's length. When the sources' layout is given, one task per position does
both steps (the merged radiance goes straight into the unmixing); when it is to be found
in the data, the merge comes first, the layout is found at three positions, and a second
pass over the results file unmixes.

A run still being written is processed as far as it goes: the positions complete when it
is opened (``ProcessReport.partial`` says so).

Modules: :mod:`~processing.light_run.run` (:func:`process_run`, the passes),
:mod:`~processing.light_run.position` (the work of one position),
:mod:`~processing.light_run.noise` (the merge's noise model),
:mod:`~processing.light_run.from_data` (the sources and the camera's numbers found in the
data), :mod:`~processing.light_run.samples` (the estimator, the samples),
:mod:`~processing.light_run.light_fit` (the fits and the light model) and
:mod:`~processing.light_run.outputs` (the files written at the end).
"""

from processing.light_run.errors import ProcessingError
from processing.light_run.position import warm_up_worker
from processing.light_run.records import ProcessReport
from processing.light_run.run import process_run

__all__ = ["process_run", "warm_up_worker", "ProcessReport", "ProcessingError"]

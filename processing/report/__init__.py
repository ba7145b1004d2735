"""The run's report: one self-contained HTML page that shows the measured light.

:func:`write_report` turns a :class:`~processing.lightmodel.LightModel` (and, when they are
at hand, the run file, the per-position samples and the pipeline's
:class:`~processing.light_run.records.ProcessReport`) into a single HTML file whose figures are
embedded as base64 PNG: no external asset, so the file can be mailed or archived alone.
A person should understand the light from the figures without reading the numbers:

1. the header: run, rig, date, units, the estimator and why it was chosen, the spatial
   resolution the camera allows on the light plane, the noise model;
2. per source, a half-polar plot of its radiant intensity ``I_s(θ)`` (the reference
   paper's Figs. 6 and 8): samples, the fit (solid where the samples cover θ, dashed where
   it extrapolates), the chief-ray cell sums for comparison and, for a simulated run, the
   truth;
3. the sources on the light plane with the footprint of one pixel drawn to scale;
4. the θ each source was sampled at, position by position;
5. how the ball widens the angles (the paper's Fig. 5): outgoing θ against the deflection
   the ball gives each chief ray, at the middle position;
6. the residuals of every fit, its reduced χ² and its parameters with uncertainties;
7. the calibration check (measured against described ball centre, and what 1 mm of error
   in the ball's position costs in angle);
8. a strip of the HDR previews over the sweep.

The polar plots show θ *signed by side*: the sweep carries the light past the ball, so its
samples leave on both sides of the light's axis; a sample whose azimuth lies within 90° of
the sweep's main azimuth ``φ_s`` is drawn at +θ, the others at −θ.

The figures are drawn with matplotlib's Agg canvas directly (no pyplot, no global
backend), laid out by hand (no layout engine), the half discs on plain axes (no polar
projection); one worker thread encodes their PNGs and does the calibration's sensitivity
and the previews while the next figure is drawn: what the report costs is mostly
matplotlib's text rendering. Given the processing's Dask cluster (``compute=``), its
workers draw the five sections that need only the model, the samples and the chief rays,
each in its own process, and the page is the same (:data:`_REMOTE_SECTIONS`). Each section
that cannot be drawn (missing inputs) says why instead; a section that fails is reported in
the page and logged, and never stops the processing.

The truth, for simulated runs, is a callable ``truth(source, theta) -> intensity`` passed by
the caller (the processing never imports the simulator). It is called with the source's
index in ``model.sources`` first and, if that raises ``LookupError`` or ``TypeError``, with
its name; ``None`` means no truth for that source.

Modules: :mod:`~processing.report.page` (:func:`write_report`), :mod:`~processing.report.sections`,
:mod:`~processing.report.figures`, :mod:`~processing.report.context` (what the figures share),
:mod:`~processing.report.markup` (HTML pieces) and :mod:`~processing.report.drawing`
(matplotlib, PNG).
"""

from processing.report.drawing import warm_up_drawing
from processing.report.figures import angles_figure, coverage_figure, layout_figure, polar_figure, residuals_figure
from processing.report.page import write_report
from processing.report.sections import NO_CALIBRATION

__all__ = [
    "NO_CALIBRATION",
    "angles_figure",
    "coverage_figure",
    "layout_figure",
    "polar_figure",
    "residuals_figure",
    "warm_up_drawing",
    "write_report",
]

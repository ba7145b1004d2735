"""Offline processing of run files: HDR merge, trace, fit, light model, exports, report, and
an object's reflectance under the measured light.

It reads run files through :mod:`drivers.contracts.runfile` and never talks to hardware.

This module is the processing's front door: the daemon, its worker and the command line take
what they call from here (an import-linter contract in ``pyproject.toml`` says so), and the
sub-packages are free to change behind it. The names load when first used (PEP 562), so that
``from processing import ProcessingOptions`` checks a request without loading NumPy's
kernels, Dask or the report's plotting: the command line starts at once and the daemon
answers a request without the processing in memory.

- a light run: :func:`process_run` with its :class:`ProcessingOptions` (the enums of their
  values, the bounds), :class:`ProcessReport`, :func:`check_outputs` (before any work),
  :func:`describe_progress` and :func:`overall_fraction` (its progress in words and as a
  share), and :func:`warm_up_worker`;
- where it runs: :func:`open_compute`, :func:`check_scheduler`, :class:`Compute`;
- its results: :class:`Results` (the HDR results file), :class:`LightModel`, :func:`run_name`;
- an object: :func:`reflectance_from_run` with :class:`ReflectanceSettings`, giving a
  :class:`ReflectanceResult`; before its run, :func:`highlight_coverage` (which points a
  schedule shows a highlight on, a :class:`HighlightCoverage`) and :func:`write_coverage`;
- the ball's position from a photograph: :func:`calibrate_ball` and its helpers;
- the camera's photometric scale from a reference: :func:`calibrate_photometry` with a
  :class:`LampReference` or a :class:`MeterReference`;
- the errors, each one line that names the file, the field or the option.
"""

from __future__ import annotations

import ast
import functools
import importlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from processing.calibration import (
        CalibrationError,
        angle_sensitivity,
        calibrate_ball,
        compare_with_rig,
        mosaic_luminance,
    )
    from processing.calibration.photometric import LampReference, MeterReference, PhotometryError
    from processing.calibration.photometric import calibrate as calibrate_photometry
    from processing.hdr.model import HDRError
    from processing.light_run.checksums import CorruptRunError, skipped_line
    from processing.light_run.errors import ProcessingError
    from processing.light_run.output_guard import check_outputs
    from processing.light_run.position import warm_up_worker
    from processing.light_run.progress import BY_NAME as STEP_BY_NAME
    from processing.light_run.progress import describe as describe_progress
    from processing.light_run.progress import overall_fraction
    from processing.light_run.records import ProcessReport
    from processing.light_run.run import process_run
    from processing.lightmodel import LightModel, LightModelError
    from processing.options import (
        DEFAULT_RAYS,
        FLAG_CHOICE,
        MAX_LUMENS,
        MAX_NAME,
        MAX_RAYS,
        MIN_RAYS,
        NAME_PATTERN,
        Estimator,
        Extrapolation,
        FitChoice,
        FitMethod,
        HDRMethod,
        NoiseSource,
        Option,
        OptionsError,
        ProcessingOptions,
        ReflectanceThresholds,
        Units,
        declared_options,
    )
    from processing.parallel import Compute, ComputeError, check_scheduler, open_compute
    from processing.reflectance.codes import ReflectanceError, ReflectanceSettings
    from processing.reflectance.coverage import HighlightCoverage, highlight_coverage, write_coverage
    from processing.reflectance.estimate import ReflectanceResult
    from processing.reflectance.run import reflectance_from_run
    from processing.results import Results, ResultsError, run_name
    from processing.steps import Step, StepsError, resolve_steps
    from processing.unmixing.sources import Source, SourcesError, layout_from_dict, load_layout

__all__ = [
    "CalibrationError",
    "Compute",
    "ComputeError",
    "CorruptRunError",
    "DEFAULT_RAYS",
    "Estimator",
    "Extrapolation",
    "FLAG_CHOICE",
    "FitChoice",
    "FitMethod",
    "HDRError",
    "HDRMethod",
    "HighlightCoverage",
    "LampReference",
    "LightModel",
    "LightModelError",
    "MAX_LUMENS",
    "MAX_NAME",
    "MAX_RAYS",
    "MIN_RAYS",
    "MeterReference",
    "NAME_PATTERN",
    "NoiseSource",
    "Option",
    "OptionsError",
    "PhotometryError",
    "ProcessReport",
    "ProcessingError",
    "ProcessingOptions",
    "ReflectanceError",
    "ReflectanceResult",
    "ReflectanceSettings",
    "ReflectanceThresholds",
    "Results",
    "ResultsError",
    "STEP_BY_NAME",
    "Source",
    "SourcesError",
    "Step",
    "StepsError",
    "Units",
    "angle_sensitivity",
    "calibrate_ball",
    "calibrate_photometry",
    "check_outputs",
    "check_scheduler",
    "compare_with_rig",
    "declared_options",
    "describe_progress",
    "highlight_coverage",
    "layout_from_dict",
    "load_layout",
    "mosaic_luminance",
    "open_compute",
    "overall_fraction",
    "process_run",
    "reflectance_from_run",
    "resolve_steps",
    "run_name",
    "skipped_line",
    "warm_up_worker",
    "write_coverage",
]


@functools.cache
def _front_door() -> dict[str, tuple[str, str]]:
    """Where each name of :data:`__all__` lives, ``name: (module, name there)``, read from the
    imports for the type checkers above: the one list of what the front door holds."""
    tree = ast.parse(Path(__file__).read_text(encoding="utf-8"))
    guarded = next(node for node in tree.body if isinstance(node, ast.If))
    return {
        alias.asname or alias.name: (str(node.module), alias.name)
        for node in guarded.body
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
    }


def __getattr__(name: str) -> Any:
    """Load a name of the front door from its module when it is first asked for (PEP 562)."""
    if name not in __all__:
        raise AttributeError(f"module 'processing' has no attribute {name!r}")
    module, attribute = _front_door()[name]
    value = getattr(importlib.import_module(module), attribute)
    globals()[name] = value  # the next look-up finds it without this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})

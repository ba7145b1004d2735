"""What a run's processing will do, decided once from its options, before any position is read."""

from __future__ import annotations

from dataclasses import dataclass

from processing.light_run.errors import ProcessingError
from processing.options import FitChoice, ProcessingOptions
from processing.steps import Step
from processing.unmixing.sources import Source, SourcesError, load_layout


@dataclass(frozen=True)
class CameraFits:
    """Which of the rig's numbers the sources step fits to the data.

    Attributes
    ----------
    fit_aperture, fit_sensor_distance : bool
        The camera's aperture diameter, its sensor distance, fitted to the data.
    aperture_fit_required, sensor_distance_fit_required : bool
        A fit that fails fails the processing (``FitChoice.ALWAYS``); otherwise it is said
        and the rig's number (or the last one fitted) kept.
    calibrate_rig : bool
        The rig's geometry fitted to the data with the sources (the self-calibration); it
        fits the aperture and the sensor distance with the rest, so neither is fitted alone.
    """

    fit_aperture: bool
    fit_sensor_distance: bool
    aperture_fit_required: bool
    sensor_distance_fit_required: bool
    calibrate_rig: bool = False

    @property
    def fits_camera(self) -> bool:
        return self.fit_aperture or self.fit_sensor_distance or self.calibrate_rig


@dataclass(frozen=True)
class ProcessingPlan:
    """What is given and what is fitted.

    The fits hang on one thing the plan is made before: how many positions are merged, known
    only once the frames are read through their checksums (``AUTO`` holds the rig on a short
    sweep). So the plan holds both answers, decided together, and :meth:`camera` picks one.

    Attributes
    ----------
    options : ProcessingOptions
        What was asked.
    layout : tuple of Source, or None
        The sources, given (loaded from ``options.layout``); None where they are searched
        for in the data.
    long_sweep : CameraFits
        The fits with :data:`RIG_FIT_MIN_POSITIONS` merged positions or more.
    short_sweep : CameraFits
        The fits with fewer: they differ from ``long_sweep`` only where ``AUTO`` would
        self-calibrate, that is where the sources are searched for (never in a fused pass).
    """

    options: ProcessingOptions
    layout: tuple[Source, ...] | None
    long_sweep: CameraFits
    short_sweep: CameraFits
    #: ``--refine-point-spread``: "never", "needed" (where the templates' χ² asks for it), "always".
    point_spread: str = "never"

    def camera(self, positions: int) -> CameraFits:
        """The fits for ``positions`` merged positions."""
        return self.long_sweep if positions >= RIG_FIT_MIN_POSITIONS else self.short_sweep

    @property
    def merge(self) -> bool:
        """The brackets are merged (the ``hdr`` step)."""
        return Step.HDR in self.options.steps

    @property
    def estimate(self) -> bool:
        """The sources are estimated and fitted (the ``sources`` step)."""
        return Step.SOURCES in self.options.steps

    @property
    def search(self) -> bool:
        """The sources are searched for in the merged positions."""
        return self.estimate and self.layout is None

    @property
    def fused(self) -> bool:
        """One task per position merges and estimates: the layout is given and nothing is fitted
        before the estimate (with a layout given, the long and the short sweep fit alike)."""
        return (
            self.merge
            and self.estimate
            and self.layout is not None
            and not self.long_sweep.fits_camera
            and self.point_spread == "never"
        )

    @property
    def passes(self) -> int:
        """Passes over the positions."""
        return int(self.merge) + int(self.estimate and not self.fused)


#: The merged positions the self-calibration needs before ``AUTO`` runs it: the rig's turns about
#: the ball and the sources' places move the light alike at any one position, and only a sweep
#: long enough tells them apart. On twelve positions of the demo's coarse rig (a sixth of the
#: default sweep) the fit drifts along that valley from run to run: the sources 0.2-1.1 mm off
#: together and the fits up to 8 % of peak, where the rig held and the aperture fitted stay near
#: 1 %; on the whole sweep it is what docs/self-calibration.md measures.
RIG_FIT_MIN_POSITIONS = 24


#: How far the measured point spread's Fresnel number may be from the run's before the
#: processing warns: 1 % moves the pattern's peak by about 1 % (docs/lab-guide.md).
FRESNEL_MISMATCH_WARNING = 0.01


def plan_processing(options: ProcessingOptions, point_spread_measured: bool = False) -> ProcessingPlan:
    """The plan for ``options``: the given layout loaded, each ``FitChoice.AUTO`` decided.

    ``AUTO`` fits the rig where the sources are searched for in the data: a search explains a
    wrong point spread or a misplaced ball with sources that are not there, which a given
    layout cannot do. The self-calibration fits the aperture and the sensor distance with the
    rest of the rig, so where it runs neither is fitted alone. With fewer merged positions than
    :data:`RIG_FIT_MIN_POSITIONS` (the plan's ``short_sweep``), ``AUTO`` holds the rig (and fits
    the aperture alone where it searches). With the camera's point spread measured
    (``point_spread_measured``) no aperture changes the templates, so the aperture is not fitted,
    and the point spread is not refined. ``AUTO`` refines it where the sources are searched for,
    if the templates' χ² asks for it (``point_spread`` "needed").

    Raises
    ------
    ProcessingError
        The layout file cannot be read, or a camera number is to be fitted alone where the
        self-calibration fits it (one line naming it).

    Examples
    --------
    >>> plan = plan_processing(ProcessingOptions.checked(steps="hdr,sources"))
    >>> fits = plan.camera(RIG_FIT_MIN_POSITIONS)
    >>> plan.search, fits.calibrate_rig, fits.fit_aperture, fits.fit_sensor_distance, plan.passes
    (True, True, False, False, 2)
    >>> plan = plan_processing(ProcessingOptions.checked(steps="hdr,sources", calibrate_rig="never"))
    >>> plan.long_sweep.calibrate_rig, plan.long_sweep.fit_aperture, plan.long_sweep.aperture_fit_required
    (False, True, False)
    >>> plan_processing(ProcessingOptions.checked(steps="hdr,sources")).camera(3).calibrate_rig
    False
    >>> plan_processing(ProcessingOptions.checked(steps="hdr,sources")).point_spread
    'needed'
    """
    layout = None
    if Step.SOURCES in options.steps and options.layout is not None:
        try:
            layout = tuple(load_layout(options.layout))
        except SourcesError as exc:
            raise ProcessingError(str(exc)) from None
    searched = Step.SOURCES in options.steps and layout is None

    def wanted(choice: FitChoice) -> bool:
        return choice is FitChoice.ALWAYS or (choice is FitChoice.AUTO and searched)

    def fits(calibrate: bool) -> CameraFits:
        return CameraFits(
            fit_aperture=wanted(options.fit_aperture) and not calibrate and not point_spread_measured,
            fit_sensor_distance=wanted(options.fit_sensor_distance) and not calibrate,
            aperture_fit_required=options.fit_aperture is FitChoice.ALWAYS,
            sensor_distance_fit_required=options.fit_sensor_distance is FitChoice.ALWAYS,
            calibrate_rig=calibrate,
        )

    calibrate = wanted(options.calibrate_rig)  # on a long sweep; a short one only where asked always
    for name, choice in (
        ("--fit-aperture", options.fit_aperture),
        ("--fit-sensor-distance", options.fit_sensor_distance),
    ):
        if name == "--fit-aperture" and point_spread_measured and choice is FitChoice.ALWAYS:
            raise ProcessingError(
                "--fit-aperture always: the rig's camera has a measured point spread "
                "(camera.measured_point_spread), which no aperture changes"
            )
        if calibrate and choice is FitChoice.ALWAYS:
            raise ProcessingError(
                f"{name} always: the self-calibration fits it with the rest of the rig "
                "(--calibrate-rig never to fit it alone)"
            )
    if point_spread_measured and options.refine_point_spread is FitChoice.ALWAYS:
        raise ProcessingError(
            "--refine-point-spread always: the rig's camera has a measured point spread "
            "(camera.measured_point_spread), which is used as measured"
        )
    if point_spread_measured or not wanted(options.refine_point_spread):
        point_spread = "never"
    else:
        point_spread = "always" if options.refine_point_spread is FitChoice.ALWAYS else "needed"
    return ProcessingPlan(
        options,
        layout,
        long_sweep=fits(calibrate),
        short_sweep=fits(options.calibrate_rig is FitChoice.ALWAYS),
        point_spread=point_spread,
    )

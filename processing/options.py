"""What a run's processing may be asked: every option with a fixed set of values, as an enum.

The command line, the daemon's job requests and :func:`processing.light_run.process_run`
take the same options; :meth:`ProcessingOptions.checked` turns what a caller gives (enum
members or their names) into one frozen record, or refuses it in one line naming the option,
before any work is done. This module imports nothing heavy, so that the command line and the
daemon can check a request without loading the processing.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, fields
from enum import StrEnum
from pathlib import Path
from typing import Any

from processing.steps import Step, StepsError, resolve_steps

#: The TM-25 ray count: the default, and the bounds a request may ask for (vendors ship
#: 0.1 to 20 million rays; the file takes 28 bytes a ray).
DEFAULT_RAYS = 100_000
MIN_RAYS, MAX_RAYS = 1_000, 50_000_000
#: The most lumens a lamp flux may be, and candela per model unit (no light comes close).
MAX_LUMENS = 1e9
#: The longest name the light files take (manufacturer, luminaire, lamp), and what one is:
#: on one line (no control characters), starting with neither a space nor a control character.
#: The daemon's job request carries the same pattern in its schema.
MAX_NAME = 200
NAME_PATTERN = r"^[^\x00-\x20\x7f][^\x00-\x1f\x7f]*$"


class OptionsError(ValueError):
    """An option the processing does not know, or a value it does not take (one line naming the option)."""


class HDRMethod(StrEnum):
    """How a raw bracket is merged (:data:`processing.hdr.brackets.RAW_METHODS`)."""

    OPTIMAL = "optimal"  # minimum-variance weights t²/σ²
    POISSON = "poisson"  # Σ y / Σ t


class NoiseSource(StrEnum):
    """Where the merge's noise model (gain, read noise) comes from."""

    AUTO = "auto"  # estimated from the brackets, the rig's figures where they allow no estimate
    ESTIMATED = "estimated"  # estimated, or the processing fails
    RIG = "rig"  # the rig description's camera figures


class Estimator(StrEnum):
    """How every source's intensity is taken from a merged position."""

    AUTO = "auto"  # from the point spread's footprint against the sources' spacing
    TEMPLATES = "templates"  # unmixing with the sources' templates
    CELL_SUMS = "cell-sums"  # flux-conserving chief-ray cell sums


class FitMethod(StrEnum):
    """The model every source's samples are fitted to (:data:`processing.fit.FIT_METHODS`)."""

    GAUSSIAN = "gaussian"
    POLYNOMIAL = "polynomial"
    COS_POWER = "cos-power"
    GAUSSIAN_2D = "gaussian-2d"


class Units(StrEnum):
    """The light model's intensity units."""

    RELATIVE = "relative"
    WATTS_PER_SR = "W/sr"


class FitChoice(StrEnum):
    """Whether some of the rig's numbers (the camera's aperture diameter, its sensor distance,
    the rig's geometry in the self-calibration) are fitted to the data."""

    AUTO = "auto"  # fitted where the sources are searched for in the data; a failed fit keeps the rig's number
    ALWAYS = "always"  # fitted; a failed fit fails the processing
    NEVER = "never"  # the rig's number


class Extrapolation(StrEnum):
    """What the light files (IES, LDT) hold beyond the θ the sweep measured (:mod:`processing.photometry`)."""

    FITTED = "fitted"  # the fits' extrapolation
    NONE = "none"  # zero: the measured range only


@dataclass(frozen=True)
class ProcessingOptions:
    """Everything a run's processing is asked, checked.

    Attributes
    ----------
    steps : tuple of Step
        The steps, in the order they run.
    method : HDRMethod
    noise : NoiseSource
    layout : Path or None
        The sources' layout (TOML); None: the sources are searched for in the data.
    estimator : Estimator
    fit_method : FitMethod
    units : Units
    ball_centre : (x, y, z) or None
        The measured ball centre in metres (rig frame); None: the rig's.
    images : bool
        An OpenEXR and a PNG preview per position (the ``hdr`` step).
    fit_aperture, fit_sensor_distance : FitChoice
        Whether the camera's aperture diameter and its sensor distance are fitted to the data
        on their own (the self-calibration fits both with the rest).
    calibrate_rig : FitChoice
        Whether the rig's geometry is fitted to the data (the self-calibration,
        :mod:`processing.light_run.self_calibration`): ``auto`` where the sources are searched
        for, ``always`` with a given layout too (its places then held).
    ignore_corrupt : bool
        Process the positions whose frames read back, skipping those with a frame that fails its
        checksum (and a corrupt ambient calibration set); without it such a frame stops the
        processing before any work.
    overwrite : bool
        Write over outputs already in the folder that another run's processing wrote (or whose
        run is unknown); without it they stop the processing before any work.
    extrapolation : Extrapolation
        What the IES and LDT files hold beyond the θ the sweep measured: the fits'
        extrapolation (``fitted``) or zero (``none``); the files, the light model's
        ``photometry`` and the report say which.
    lamp_lumens : float or None
        The lamp's flux (lm): the IES and LDT files' relative intensities are scaled to it.
    candela_per_unit : float or None
        Absolute photometry: candela per unit of the light model's intensity (a calibration
        against a reference); the IES and LDT files are then in candela. Not with
        ``lamp_lumens``.
    manufacturer, luminaire, lamp : str or None
        Names the light files carry (IES ``[MANUFAC]``, ``[LUMINAIRE]``, ``[LAMP]``; the LDT's
        company, luminaire and lamp type; the TM-25 manufacturer and name fields).
    rays : int
        The TM-25 ray file's number of rays (:data:`MAX_RAYS` at most; written in blocks, so
        memory stays bounded).

    Examples
    --------
    >>> options = ProcessingOptions.checked(steps="hdr,sources", fit_aperture="always")
    >>> options.fit_aperture, options.method
    (<FitChoice.ALWAYS: 'always'>, <HDRMethod.OPTIMAL: 'optimal'>)
    >>> ProcessingOptions.checked(method="bogus")
    Traceback (most recent call last):
    ...
    processing.options.OptionsError: --method: 'bogus' is not one of optimal, poisson
    """

    steps: tuple[Step, ...] = (Step.HDR,)
    method: HDRMethod = HDRMethod.OPTIMAL
    noise: NoiseSource = NoiseSource.AUTO
    layout: Path | None = None
    estimator: Estimator = Estimator.AUTO
    fit_method: FitMethod = FitMethod.GAUSSIAN
    units: Units = Units.RELATIVE
    ball_centre: tuple[float, float, float] | None = None
    images: bool = True
    fit_aperture: FitChoice = FitChoice.AUTO
    fit_sensor_distance: FitChoice = FitChoice.NEVER
    calibrate_rig: FitChoice = FitChoice.AUTO
    ignore_corrupt: bool = False
    overwrite: bool = False
    extrapolation: Extrapolation = Extrapolation.FITTED
    lamp_lumens: float | None = None
    candela_per_unit: float | None = None
    manufacturer: str | None = None
    luminaire: str | None = None
    lamp: str | None = None
    rays: int = DEFAULT_RAYS

    @classmethod
    def checked(cls, **values: Any) -> ProcessingOptions:
        """The options from enum members or their names (``steps`` also as ``"hdr,sources"``).

        Raises
        ------
        OptionsError
            One line naming the option (as the command line spells it) and what it takes.
        """
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise OptionsError(f"{unknown[0]}: not an option of the processing (known: {', '.join(sorted(known))})")
        out = {}
        for f in fields(cls):
            if f.name not in values or values[f.name] is None and f.name not in ("layout", "ball_centre"):
                continue
            out[f.name] = _CHECKS.get(f.name, _as_is)(f.name, values[f.name])
        if out.get("lamp_lumens") is not None and out.get("candela_per_unit") is not None:
            raise OptionsError(
                "--lamp-lumens, --candela-per-unit: give one (relative intensities scaled to a lamp flux, or "
                "absolute candela), not both"
            )
        return cls(**out)


def _option(name: str) -> str:
    return "--" + name.replace("_", "-").replace("fit-method", "fit")


def _member(enum: type[StrEnum]) -> Callable[[str, Any], StrEnum]:
    def check(name: str, value: Any) -> StrEnum:
        try:
            return enum(value)
        except ValueError:
            choices = ", ".join(member.value for member in enum)
            raise OptionsError(f"{_option(name)}: {value!r} is not one of {choices}") from None

    return check


def _steps(name: str, value: Any) -> tuple[Step, ...]:
    try:
        return resolve_steps(value)
    except StepsError as exc:
        raise OptionsError(f"--steps: {exc}") from None


def _path(name: str, value: Any) -> Path | None:
    return None if value is None else Path(value)


def _point(name: str, value: Any) -> tuple[float, float, float] | None:
    if value is None:
        return None
    try:
        point = tuple(float(v) for v in (value.split(",") if isinstance(value, str) else value))
    except (TypeError, ValueError):
        point = ()
    if len(point) != 3 or not all(math.isfinite(v) for v in point):
        raise OptionsError(f"{_option(name)}: expected X,Y,Z in metres, got {value!r}")
    return point


def _flag(name: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise OptionsError(f"{_option(name)}: expected true or false, got {value!r}")
    return value


def _positive(name: str, value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool) or not (0 < number <= MAX_LUMENS):
        raise OptionsError(f"{_option(name)}: expected a positive number up to {MAX_LUMENS:g}, got {value!r}")
    return number


def _rays(name: str, value: Any) -> int:
    try:
        count = int(value) if not isinstance(value, bool) and float(value) == int(value) else None
    except (TypeError, ValueError, OverflowError):
        count = None
    if count is None or not MIN_RAYS <= count <= MAX_RAYS:
        raise OptionsError(
            f"{_option(name)}: expected a whole number of rays from {MIN_RAYS} to {MAX_RAYS}, got {value!r}"
        )
    return count


def _name(name: str, value: Any) -> str:
    """A name the light files carry (:data:`NAME_PATTERN`, :data:`MAX_NAME` characters at most)."""
    if not isinstance(value, str) or len(value) > MAX_NAME or not re.fullmatch(NAME_PATTERN, value):
        raise OptionsError(
            f"{_option(name)}: expected a name of 1 to {MAX_NAME} characters on one line, not starting with a "
            f"space, got {value!r}"
        )
    return value


def _as_is(name: str, value: Any) -> Any:
    return value


_CHECKS: dict[str, Callable[[str, Any], Any]] = {
    "steps": _steps,
    "method": _member(HDRMethod),
    "noise": _member(NoiseSource),
    "layout": _path,
    "estimator": _member(Estimator),
    "fit_method": _member(FitMethod),
    "units": _member(Units),
    "ball_centre": _point,
    "images": _flag,
    "fit_aperture": _member(FitChoice),
    "fit_sensor_distance": _member(FitChoice),
    "calibrate_rig": _member(FitChoice),
    "ignore_corrupt": _flag,
    "overwrite": _flag,
    "extrapolation": _member(Extrapolation),
    "lamp_lumens": _positive,
    "candela_per_unit": _positive,
    "manufacturer": _name,
    "luminaire": _name,
    "lamp": _name,
    "rays": _rays,
}

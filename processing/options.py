"""What a run's processing may be asked: every option declared once, every fixed set of values an enum.

Each option is one :class:`Option` record, the metadata of its field in the record it belongs
to (:class:`ProcessingOptions`, :class:`ReflectanceThresholds`): its name, type, default,
bounds, help text and choices. From these records are built the Python API (the frozen
records and their checks), the ``mirrorgonio process`` and ``mirrorgonio reflectance``
commands' options (:mod:`acquisition.cli.app`) and the daemon's job request
(:mod:`acquisition.daemon.models`), so the three say the same. :meth:`ProcessingOptions.checked`
turns what a caller gives (enum members or their names) into one frozen record, or refuses it
in one line naming the option, before any work is done. This module imports nothing heavy, so
that the command line and the daemon can check a request without loading the processing.
"""

from __future__ import annotations

import math
import re
import textwrap
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from enum import StrEnum
from pathlib import Path
from typing import Any, ClassVar, Union, get_args, get_origin, get_type_hints

from processing.steps import Step, StepsError, resolve_steps

#: The TM-25 ray count: the default, and the bounds a request may ask for (vendors ship
#: 0.1 to 20 million rays; the file takes 28 bytes a ray).
DEFAULT_RAYS = 100_000
MIN_RAYS, MAX_RAYS = 1_000, 50_000_000
#: The most lumens a lamp flux may be, and candela per model unit (no light comes close).
MAX_LUMENS = 1e9
#: The longest name the light files take (manufacturer, luminaire, lamp), and what one is:
#: on one line (no control characters), starting with neither a space nor a control character.
MAX_NAME = 200
NAME_PATTERN = r"^[^\x00-\x20\x7f][^\x00-\x1f\x7f]*$"
#: What a request's steps look like before they are resolved (names, comma-separated).
STEPS_PATTERN = r"^[a-z]+(,[a-z]+)*$"
#: The longest path a request may name (a layout file on the worker's machine).
MAX_PATH = 4096


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


#: A :class:`FitChoice` option as a command line flag: neither flag given, ``--FLAG``, ``--no-FLAG``.
FLAG_CHOICE = {None: FitChoice.AUTO, True: FitChoice.ALWAYS, False: FitChoice.NEVER}


class Extrapolation(StrEnum):
    """What the light files (IES, LDT) hold beyond the θ the sweep measured (:mod:`processing.photometry`)."""

    FITTED = "fitted"  # the fits' extrapolation
    NONE = "none"  # zero: the measured range only


#: An :class:`Option`'s ``front_default`` when the command line and a job take the Python default.
SAME: Any = object()


@dataclass(frozen=True)
class Option:
    """One option, declared once; the Python API, the command line and the job request are built from it.

    Attributes
    ----------
    default : object
        The Python API's default (the record's field default).
    help : str
        What the option does, one text for every surface; ``{name}`` names another option as the
        surface spells it (``--lamp-lumens`` on the command line, ``lamp_lumens`` in a job):
        :meth:`help_as`.
    kind : type
        What a command or a request gives: ``str``, ``int``, ``float``, ``bool``, ``Path`` or a
        ``StrEnum`` (its members are the choices); None: the field's type, without None.
    name : str
        The field's name (filled in by :func:`declared_options`).
    public : str
        The name the command line (``--public-name``) and a job (``public_name``) take;
        default: ``name``.
    cli, job : bool
        Whether the command line, and the daemon's job request, take the option.
    front_default : object
        The command line's and the job's default, where it is not the Python API's
        (:data:`SAME`).
    minimum, maximum : float or None
        Bounds of a number, inclusive unless ``exclusive_minimum`` or ``exclusive_maximum``.
    unit : str
        What a number counts (``rays``, ``degrees``), for its error message.
    min_length, max_length, pattern : int, int, str or None
        What a string may be (the job's schema carries them).
    check : callable or None
        ``check(option, value) -> value``, raising :class:`OptionsError`; default: by ``kind``.
    """

    default: Any
    help: str
    kind: Any = None
    name: str = ""
    public: str = ""
    cli: bool = True
    job: bool = False
    front_default: Any = SAME
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    exclusive_maximum: bool = False
    unit: str = ""
    min_length: int | None = None
    max_length: int | None = None
    pattern: str | None = None
    check: Callable[[Option, Any], Any] | None = None

    @property
    def flag(self) -> str:
        """The option as the command line spells it (``--fit``)."""
        return "--" + self.public.replace("_", "-")

    @property
    def given_default(self) -> Any:
        """The default of the command line and of the job request."""
        return self.default if self.front_default is SAME else self.front_default

    @property
    def choices(self) -> type[StrEnum] | None:
        """The enum whose values the option takes, or None."""
        return self.kind if isinstance(self.kind, type) and issubclass(self.kind, StrEnum) else None

    def help_as(self, spell: Callable[[str], str]) -> str:
        """The help text, every option it names spelled by ``spell(public_name)``."""
        return self.help.format_map(_Spelled(spell))

    def checked(self, value: Any) -> Any:
        """``value`` as the option takes it; :class:`OptionsError` naming the option otherwise."""
        return (self.check or _check_by_kind(self.kind))(self, value)


class _Spelled(dict[str, str]):
    def __init__(self, spell: Callable[[str], str]) -> None:
        super().__init__()
        self.spell = spell

    def __missing__(self, key: str) -> str:
        return self.spell(key)


def option(default: Any, help: str, **declared: Any) -> Any:
    """A record's field declared as an :class:`Option` (``declared``: its other attributes)."""
    return field(default=default, metadata={"option": Option(default, help, **declared)})


def declared_options(record: type) -> tuple[Option, ...]:
    """The options of a record whose fields are declared with :func:`option`, in their order."""
    if record not in _DECLARED:
        _DECLARED[record] = _declared(record)
    return _DECLARED[record]


#: :func:`declared_options` by record, each worked out once (a record is checked at every creation).
_DECLARED: dict[type, tuple[Option, ...]] = {}


def _declared(record: type) -> tuple[Option, ...]:
    hints = get_type_hints(record)
    found = []
    for f in fields(record):
        declared = f.metadata["option"]
        kind = declared.kind if declared.kind is not None else _without_none(hints[f.name])
        found.append(replace(declared, name=f.name, public=declared.public or f.name, kind=kind))
    return tuple(found)


def _without_none(hint: Any) -> Any:
    if get_origin(hint) is Union or type(hint).__name__ == "UnionType":
        (kind,) = (arg for arg in get_args(hint) if arg is not type(None))
        return kind
    return hint


def attributes_section(record: type) -> str:
    """A numpydoc ``Attributes`` section of the record's options, from their help texts."""
    lines = ["Attributes", "----------"]
    types = {f.name: str(f.type) for f in fields(record)}
    for declared in declared_options(record):
        lines.append(f"{declared.name} : {types[declared.name]}")
        text = declared.help_as(lambda name: f"``{name}``")
        lines += textwrap.wrap(text, width=96, initial_indent="    ", subsequent_indent="    ")
    return "\n".join(lines)


def _with_attributes(record: type) -> str | None:
    """The record's docstring with its :func:`attributes_section` before its examples."""
    if record.__doc__ is None:  # python -OO
        return None
    summary, marker, examples = record.__doc__.partition("    Examples\n")
    section = "\n".join("    " + line if line else line for line in attributes_section(record).splitlines())
    return f"{summary.rstrip()}\n\n{section}\n\n{marker}{examples}"


# --- the checks: each takes the option and what a caller gives, returns the value or says why not


def _member(option: Option, value: Any) -> StrEnum:
    enum = option.kind
    try:
        return enum(value)
    except ValueError:
        choices = ", ".join(member.value for member in enum)
        raise OptionsError(f"{option.flag}: {value!r} is not one of {choices}") from None


def _steps(option: Option, value: Any) -> tuple[Step, ...]:
    try:
        return resolve_steps(value)
    except StepsError as exc:
        raise OptionsError(f"{option.flag}: {exc}") from None


def _path(option: Option, value: Any) -> Path | None:
    return None if value is None else Path(value)


def _point(option: Option, value: Any) -> tuple[float, float, float] | None:
    if value is None:
        return None
    try:
        point = tuple(float(v) for v in (value.split(",") if isinstance(value, str) else value))
    except (TypeError, ValueError):
        point = ()
    if len(point) != 3 or not all(math.isfinite(v) for v in point):
        raise OptionsError(f"{option.flag}: expected X,Y,Z in metres, got {value!r}")
    return (point[0], point[1], point[2])


def _flag(option: Option, value: Any) -> bool:
    if not isinstance(value, bool):
        raise OptionsError(f"{option.flag}: expected true or false, got {value!r}")
    return value


def _number(option: Option, value: Any) -> float | int:
    """A number within the option's bounds (a whole one for an ``int`` option)."""
    whole = option.kind is int
    try:
        number = float(value)
        if whole and number != int(number):
            number = math.nan
    except (TypeError, ValueError, OverflowError):
        number = math.nan
    low, high = option.minimum, option.maximum
    within = not isinstance(value, bool) and not math.isnan(number)
    if within and low is not None:
        within = number > low if option.exclusive_minimum else number >= low
    if within and high is not None:
        within = number < high if option.exclusive_maximum else number <= high
    if not within:
        raise OptionsError(f"{option.flag}: expected {_described_range(option)}, got {value!r}")
    return int(number) if whole else number


def _described_range(option: Option) -> str:
    """What :func:`_number` takes, in words: ``a whole number of rays from 1000 to 50000000``."""
    low, high = option.minimum, option.maximum
    shown = (lambda v: str(int(v))) if option.kind is int else (lambda v: f"{v:g}")
    positive = low == 0 and option.exclusive_minimum
    what = ("a positive " if positive else "a ") + ("whole number" if option.kind is int else "number")
    what += f" of {option.unit}" if option.unit else ""
    if positive:
        return what if high is None else f"{what} up to {shown(high)}"
    if low is not None and high is not None:
        return f"{what} from {shown(low)} to {'under ' if option.exclusive_maximum else ''}{shown(high)}"
    if low is not None:
        return f"{what} of {'over' if option.exclusive_minimum else 'at least'} {shown(low)}"
    return what


def _name(option: Option, value: Any) -> str:
    """A name the light files carry (:data:`NAME_PATTERN`, :data:`MAX_NAME` characters at most)."""
    if not isinstance(value, str) or len(value) > MAX_NAME or not re.fullmatch(NAME_PATTERN, value):
        raise OptionsError(
            f"{option.flag}: expected a name of 1 to {MAX_NAME} characters on one line, not starting with a "
            f"space, got {value!r}"
        )
    return value


def _as_is(option: Option, value: Any) -> Any:
    return value


def _check_by_kind(kind: Any) -> Callable[[Option, Any], Any]:
    if isinstance(kind, type) and issubclass(kind, StrEnum):
        return _member
    return {bool: _flag, int: _number, float: _number, Path: _path}.get(kind, _as_is)


#: The names the light files carry: one declaration of what a name is.
_LIGHT_FILE_NAME: Mapping[str, Any] = {
    "job": True,
    "min_length": 1,
    "max_length": MAX_NAME,
    "pattern": NAME_PATTERN,
    "check": _name,
}
#: A photometric scale: a positive number (lumens, candela per unit).
_SCALE: Mapping[str, Any] = {"job": True, "minimum": 0.0, "exclusive_minimum": True, "maximum": MAX_LUMENS}


@dataclass(frozen=True)
class ProcessingOptions:
    """Everything a run's processing is asked, checked (each field an :class:`Option`).

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

    # The Python API's steps are the HDR merge alone (the quick look a script starts with); a
    # command or a job asked for nothing more processes the whole run.
    steps: tuple[Step, ...] = option(
        (Step.HDR,),
        "The steps, comma-separated: hdr, sources (trace and fit are names for parts of sources).",
        kind=str,
        job=True,
        front_default="hdr,sources",
        max_length=200,
        pattern=STEPS_PATTERN,
        check=_steps,
    )
    method: HDRMethod = option(
        HDRMethod.OPTIMAL, "How a bracket is merged into HDR radiance: optimal (minimum-variance weights) or poisson."
    )
    noise: NoiseSource = option(
        NoiseSource.AUTO,
        "The HDR merge's noise model: auto (estimated from the brackets, else the rig's camera figures), "
        "estimated (or the processing fails), or rig (the rig's camera figures).",
        job=True,
    )
    layout: Path | None = option(
        None,
        "The sources on the light plane (a TOML layout file; a job's is on the worker's machine). Without one "
        "the sources are found in the data.",
        job=True,
        max_length=MAX_PATH,
    )
    estimator: Estimator = option(
        Estimator.AUTO,
        "How every source's intensity is taken from a position: auto (from the point spread's footprint), "
        "templates (unmixing with the sources' templates), or cell-sums (chief-ray cell sums).",
        job=True,
    )
    fit_method: FitMethod = option(
        FitMethod.GAUSSIAN, "The model every source's I(θ) is fitted to.", public="fit", job=True
    )
    units: Units = option(Units.RELATIVE, "The light model's intensity units.", cli=False)
    ball_centre: tuple[float, float, float] | None = option(
        None,
        "The measured ball centre X,Y,Z in metres (rig frame; from `calibrate`). Without it, the rig's.",
        kind=str,
        check=_point,
    )
    images: bool = option(True, "Write an OpenEXR and a PNG preview of every position (hdr step).")
    fit_aperture: FitChoice = option(
        FitChoice.AUTO,
        "Fit the camera's aperture (pinhole) diameter to the data on its own (docs/light-model.md), where the "
        "self-calibration is off: auto where the sources are searched for in the data (no {layout}), the rig's "
        "diameter kept if that fit fails; always (a failed fit fails the processing); never (the rig's diameter).",
        job=True,
    )
    fit_sensor_distance: FitChoice = option(
        FitChoice.NEVER,
        "Fit the sensor distance (pinhole to sensor) to the data too, before the aperture, as {fit_aperture} "
        "(docs/light-model.md; it takes minutes).",
        job=True,
    )
    calibrate_rig: FitChoice = option(
        FitChoice.AUTO,
        "Fit the rig's geometry to the data with the sources (self-calibration, docs/self-calibration.md): the "
        "camera's pose, sensor distance and pinhole, the arm's base frame. auto where the sources are searched "
        "for (no {layout}); always (with a {layout} too, its places held); never. It fits the aperture and the "
        "sensor distance with the rest: their own fits then stay off.",
        job=True,
    )
    refine_point_spread: FitChoice = option(
        FitChoice.AUTO,
        "Refine the camera's point spread from the sweep (docs/light-model.md, \"The point spread from the "
        "data\"): a correction shared by every position, estimated at the fits' positions and kept where it "
        "lowers the χ² of the positions between them by a fifth. auto where the sources are searched for (no "
        "{layout}) and the templates' χ²/pixel is over 1.5; always (estimated whatever the χ², kept where it "
        "lowers the held-out χ² at all); never. Not with a measured point spread (camera.measured_point_spread).",
        job=True,
    )
    ignore_corrupt: bool = option(
        False,
        "Process the rest of a run with frames that fail their checksums: a position with a corrupt frame is "
        "skipped whole (said in the light model's provenance, the report, and the job's message or on stderr). "
        "Without it such a frame stops the processing before any work, naming the position and the frame.",
        job=True,
    )
    overwrite: bool = option(
        False,
        "Write over outputs of the same name that another run's processing wrote (or whose run is unknown). "
        "Without it they stop the processing before any work.",
    )
    extrapolation: Extrapolation = option(
        Extrapolation.FITTED,
        "What the IES and LDT files hold beyond the θ the sweep measured: fitted (the fits' extrapolation) or "
        "none (zero: the measured range only); the files say which (docs/light-model.md).",
        job=True,
    )
    lamp_lumens: float | None = option(
        None,
        "The lamp's flux in lumens: the IES and LDT files' relative intensities are scaled to it (without it "
        "the IES table is scaled to a peak of 1000). Not with {candela_per_unit}.",
        **_SCALE,
    )
    candela_per_unit: float | None = option(
        None,
        "Absolute photometry: candela per unit of the light model's intensity (from a calibration against a "
        "reference); the IES and LDT files are then in candela. Not with {lamp_lumens}.",
        **_SCALE,
    )
    photometric_calibration: Path | None = option(
        None,
        "A rig file whose [camera.photometric] (the camera's photometric scale, mirrorgonio calibrate-photometry) "
        "applies instead of the run's own rig's: for a run taken before the calibration was stored. With either, "
        "the light model, the report and the light files are in candela and lumens. Not with {candela_per_unit} "
        "or {lamp_lumens}.",
        job=True,
        max_length=MAX_PATH,
    )
    manufacturer: str | None = option(
        None, "The manufacturer the light files name (IES [MANUFAC], LDT company, TM-25).", **_LIGHT_FILE_NAME
    )
    luminaire: str | None = option(
        None,
        "The luminaire's name in the light files (IES [LUMINAIRE], LDT, TM-25 name). Without it, the run's.",
        **_LIGHT_FILE_NAME,
    )
    lamp: str | None = option(None, "The lamp's name (IES [LAMP], LDT lamp type).", **_LIGHT_FILE_NAME)
    rays: int = option(
        DEFAULT_RAYS,
        f"Rays in the TM-25 ray file, {MIN_RAYS:,} to {MAX_RAYS:,} (written in blocks: memory stays bounded; "
        "28 bytes a ray on disk).",
        job=True,
        minimum=MIN_RAYS,
        maximum=MAX_RAYS,
        unit="rays",
    )

    @classmethod
    def checked(cls, **values: Any) -> ProcessingOptions:
        """The options from enum members or their names (``steps`` also as ``"hdr,sources"``).

        None stands for the default (for an option whose default is None too: none given).

        Raises
        ------
        OptionsError
            One line naming the option (as the command line spells it) and what it takes.
        """
        known = {declared.name: declared for declared in declared_options(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise OptionsError(f"{unknown[0]}: not an option of the processing (known: {', '.join(sorted(known))})")
        out = {}
        for name, value in values.items():
            if value is not None:
                out[name] = known[name].checked(value)
        if out.get("lamp_lumens") is not None and out.get("candela_per_unit") is not None:
            raise OptionsError(
                "--lamp-lumens, --candela-per-unit: give one (relative intensities scaled to a lamp flux, or "
                "absolute candela), not both"
            )
        if out.get("photometric_calibration") is not None and (
            out.get("lamp_lumens") is not None or out.get("candela_per_unit") is not None
        ):
            raise OptionsError(
                "--photometric-calibration: not with --lamp-lumens or --candela-per-unit (one scale for the files)"
            )
        return cls(**out)


ProcessingOptions.__doc__ = _with_attributes(ProcessingOptions)


@dataclass(frozen=True)
class ReflectanceThresholds:
    """The thresholds of the reflectance estimate's sample selection (``docs/reflectance.md``), checked.

    Declared here, light, for the ``mirrorgonio reflectance`` command;
    :class:`processing.reflectance.codes.ReflectanceSettings` is this record, its refusals a
    ``ReflectanceError`` (:attr:`error`).

    Examples
    --------
    >>> ReflectanceThresholds(specular_deg=0.0).specular_deg
    0.0
    >>> ReflectanceThresholds(grazing_light_deg=90)
    Traceback (most recent call last):
    ...
    processing.options.OptionsError: --grazing-deg: expected a number of degrees from 0 to under 90, got 90
    """

    #: What a value out of bounds raises.
    error: ClassVar[type[ValueError]] = OptionsError

    grazing_light_deg: float = option(
        15.0,
        "Exclude a sample where the light (its isotropic point) stands less than this elevation above the "
        "face's plane (degrees).",
        public="grazing_deg",
        **(_ANGLE := {"minimum": 0.0, "maximum": 90.0, "exclusive_maximum": True, "unit": "degrees"}),
    )
    grazing_view_deg: float = option(
        15.0,
        "Exclude a pixel the camera sees at less than this elevation (degrees).",
        public="view_grazing_deg",
        **_ANGLE,
    )
    specular_deg: float = option(
        15.0,
        "Exclude a sample whose half vector (of the light and view directions) lies within this angle of the "
        "normal, where a specular lobe would peak (degrees; 0: off).",
        **_ANGLE,
    )
    outlier: float = option(
        0.05,
        "With 3 or more usable lights, drop the light whose radiance exceeds the other lights' fit by more than "
        "this fraction, one light at a time (inf: off).",
        minimum=0.0,
        exclusive_minimum=True,
    )
    edge_margin: int = option(
        2,
        "Superpixels by which silhouettes and depth discontinuities are dilated (excluded).",
        minimum=0,
        unit="superpixels",
    )
    shadow_margin: int = option(
        1,
        "Superpixels by which each light's cast shadow is dilated (penumbra, camera blur).",
        cli=False,
        minimum=0,
        unit="superpixels",
    )
    depth_tolerance: float = option(
        3.0,
        "A depth jump between neighbouring pixels larger than this many superpixel footprints, that neither "
        "pixel's face plane explains, is a discontinuity.",
        cli=False,
        minimum=0.0,
        exclusive_minimum=True,
    )
    min_lights: int = option(2, "Usable lights a pixel needs.", cli=False, minimum=2, unit="lights")
    hold_out: int = option(
        4,
        "Light positions left out of the BRDF fit, spread over the schedule, to check it by relighting them (0: none).",
        minimum=0,
        unit="lights",
    )
    basis: int = option(
        6,
        "At most this many basis materials lend their lobe to the points no highlight reached.",
        minimum=1,
        unit="materials",
    )

    def __post_init__(self) -> None:
        for declared in declared_options(type(self)):
            try:
                value = declared.checked(getattr(self, declared.name))
            except OptionsError as exc:
                raise self.error(str(exc)) from None
            object.__setattr__(self, declared.name, value)  # a whole number as an int


ReflectanceThresholds.__doc__ = _with_attributes(ReflectanceThresholds)

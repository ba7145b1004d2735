"""IES LM-63-2019 photometric files, type C photometry: the far field of the whole light."""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

import numpy as np

from drivers.contracts.version import __version__
from processing.colour import describe
from processing.exports.far_field import (
    ExportError,
    absolute_note,
    angle_grid,
    checked_extrapolation,
    describe_light,
    far_field_scaling,
    far_field_table,
    intensity_uncertainty,
    keyword_lines,
    luminous_opening,
    measured_range_text,
    plain_number,
    theta_cover,
    wrap_numbers,
    write_text,
)
from processing.lightmodel import LightModel
from processing.options import Extrapolation
from processing.photometry import Photometry, summarize

# LM-63-2019 §5.13, Table 2: the file generation type, matched on the exact token.
FILE_GENERATION_TYPES = {
    "1.00001": "Undefined",
    "1.00010": "Computer Simulation",
    "1.00000": "Test at an unaccredited lab",
    "1.00100": "Test at an unaccredited lab that has been lumen scaled",
    "1.01000": "Test at an unaccredited lab with interpolated angle set",
    "1.01100": "Test at an unaccredited lab with interpolated angle set that has been lumen scaled",
    "1.10000": "Test at an accredited lab",
    "1.10100": "Test at an accredited lab that has been lumen scaled",
    "1.11000": "Test at an accredited lab with interpolated angle set",
    "1.11100": "Test at an accredited lab with interpolated angle set that has been lumen scaled",
}


def _ies_angles(
    path: Path, vertical_step_deg: float, vertical_max_deg: float, horizontal_step_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """The vertical angles γ (to 90° or 180°, type C) and the horizontal angles C (to 360°), degrees."""
    if vertical_max_deg not in (90, 180):
        raise ExportError(f"{path}: vertical_max_deg: must be 90 or 180 (type C), got {vertical_max_deg!r}")
    gamma = angle_grid(path, "vertical_step_deg", vertical_step_deg, float(vertical_max_deg))
    return gamma, angle_grid(path, "horizontal_step_deg", horizontal_step_deg, 360.0)


def _ies_file_generation_type(path: Path, token: str | None, lamp_lumens: float | None) -> str:
    """The LM-63-2019 Table 2 token: the one given, else a test with an interpolated angle set (lumen scaled)."""
    if token is None:
        token = "1.01100" if lamp_lumens is not None else "1.01000"
    if token not in FILE_GENERATION_TYPES:
        raise ExportError(
            f"{path}: file_generation_type: {token!r} is not a token of LM-63-2019 Table 2 "
            f"({', '.join(FILE_GENERATION_TYPES)})"
        )
    return token


def _ies_units(
    model: LightModel, absolute: bool, calibration: float | None, lamp_lumens: float | None
) -> tuple[str, str]:
    """``([_UNITS], [OTHER])``: what the intensities are, in a word and in a sentence."""
    if absolute:
        note = absolute_note(model)
        return "candela", (
            f"Absolute photometry: candela = {calibration:.6g} cd per model unit x the model's {model.units} "
            "intensities." + (f" {note}" if note else "")
        )
    scaled = f"scaled to a lamp flux of {lamp_lumens:.6g} lm" if lamp_lumens is not None else "scaled to a peak of 1000"
    return "relative intensity", (
        f"Relative intensity, not candela: the light model is {model.units} and uncalibrated "
        f"photometrically; values {scaled}, lumens per lamp is the flux of this table."
    )


def _angle_keyword(value: float | None) -> str:
    return "undefined" if value is None else f"{value:.1f}"


def _ies_photometry_keywords(model: LightModel, summary: Photometry) -> list[str]:
    """The user keywords (LM-63-2019: ``[_…]``) of the table's photometric summary and its
    measured range: degrees, and % of the table's flux; the intensities' 1σ over that range."""
    lines = keyword_lines("_MEASURED_THETA_MAX", f"{summary.light_theta_max_deg[0]:.1f}")
    median, largest = intensity_uncertainty(model, summary.light_theta_max_deg[0])
    lines += keyword_lines(
        "_INTENSITY_UNCERTAINTY",
        f"1-sigma {100 * median:.2f} % median, {100 * largest:.2f} % largest, over the measured gamma where the "
        "intensity is at least 10 % of the peak (fits and templates' model error; a calibration's own 1-sigma "
        "adds to it)",
    )
    lines += keyword_lines("_EXTRAPOLATION", summary.extrapolation)
    lines += keyword_lines("_FLUX_BEYOND_MEASURED", f"{100 * summary.beyond_fraction:.1f} %")
    for kind in ("beam", "field"):
        for plane in ("C0-C180", "C90-C270"):
            name = f"_{kind.upper()}ANGLE_{plane.replace('-', '_')}"
            lines += keyword_lines(name, _angle_keyword(summary.angle(kind, plane)))
    _, gamma, c, symmetric = summary.peak
    return lines + keyword_lines("_PEAKDIRECTION", f"gamma {gamma:.1f} C {'any' if symmetric else f'{c:.1f}'}")


def _ies_keywords(
    model: LightModel, given: dict, manufacturer: str, grid: str, units: tuple[str, str], summary: Photometry
) -> list[str]:
    """The keyword lines: the test and the luminaire (``given``, else from the model's provenance), how
    the table was made, what its numbers are, and its photometric summary."""
    run, rig, methods = describe_light(model)
    lo, hi = theta_cover(model)
    today = _dt.date.today().isoformat()
    units_word, other = units
    lines = keyword_lines("TEST", given["TEST"] or f"mirrorgonio run {run}")
    lines += keyword_lines("TESTLAB", given["TESTLAB"] or f"mirrorgonio mirror-ball goniophotometer, rig {rig}")
    lines += keyword_lines("ISSUEDATE", given["ISSUEDATE"] or today)
    lines += keyword_lines("MANUFAC", manufacturer)
    lines += keyword_lines("LUMCAT", given["LUMCAT"] or run)
    lines += keyword_lines(
        "LUMINAIRE", given["LUMINAIRE"] or f"near-field light model of {len(model.sources)} point sources"
    )
    if given.get("LAMP"):
        lines += keyword_lines("LAMP", given["LAMP"])
    lines += keyword_lines(
        "FILEGENINFO",
        f"Far field (sum of the sources' intensities) of a light model fitted ({methods}) to a mirror-ball "
        f"goniophotometer measurement, resampled on a {grid}. "
        f"The measurement covered vertical angles {lo:.1f} to {hi:.1f} degrees; values beyond are "
        + (
            "zero (measured range only). "
            if summary.extrapolation == Extrapolation.NONE
            else "the fits' extrapolation. "
        )
        + f"Generated by mirrorgonio {__version__} on {today}.",
    )
    lines += keyword_lines("OTHER", f"{other} {measured_range_text(summary)}")
    lines += keyword_lines("_UNITS", units_word)
    lines += _ies_photometry_keywords(model, summary)
    lines += _ies_colour(model)
    return lines + keyword_lines("_SOFTWARE", f"mirrorgonio {__version__}")


def _ies_colour(model: LightModel) -> list[str]:
    """The light's colour as user keywords (LM-63-2019 has none for it): ``[_CCT]`` in kelvin,
    ``[_DUV]``, ``[_CHROMATICITY]`` and ``[_CRI]`` (not measured: it needs the spectrum); none
    where the model has no colour."""
    colour = model.chromaticity
    if not colour:
        return []
    lines = []
    if colour.get("cct_k") is not None:
        lines += keyword_lines("_CCT", f"{colour['cct_k']:.0f}")
    if colour.get("duv") is not None:
        lines += keyword_lines("_DUV", f"{colour['duv']:+.4f}")
    lines += keyword_lines("_CHROMATICITY", describe(colour))
    return lines + keyword_lines("_CRI", "not measured (a three-channel camera does not give the spectrum)")


def _ies_photometry(
    model: LightModel,
    gamma: np.ndarray,
    c: np.ndarray,
    intensities: np.ndarray,
    lumens: str,
    file_generation_type: str,
    input_watts: float,
) -> list[str]:
    """``TILT=NONE``, the lamp and ballast lines, the angles, then the intensities one C plane after another."""
    length, width = luminous_opening(model)
    lines = ["TILT=NONE", f"1 {lumens} 1 {len(gamma)} {len(c)} 1 2 {plain_number(width)} {plain_number(length)} 0"]
    lines.append(f"1.0 {file_generation_type} {plain_number(input_watts)}")
    lines += wrap_numbers(plain_number(g) for g in gamma)
    lines += wrap_numbers(plain_number(h) for h in c)
    for row in intensities:
        lines += wrap_numbers(plain_number(v) for v in row)
    return lines


def write_ies(
    model: LightModel,
    path: str | os.PathLike[str],
    *,
    calibration: float | None = None,
    lamp_lumens: float | None = None,
    vertical_step_deg: float = 1.0,
    vertical_max_deg: float = 90.0,
    horizontal_step_deg: float = 5.0,
    manufacturer: str = "unknown",
    luminaire: str | None = None,
    lamp: str | None = None,
    lumcat: str | None = None,
    test: str | None = None,
    testlab: str | None = None,
    issue_date: str | None = None,
    file_generation_type: str | None = None,
    input_watts: float = 0.0,
    extrapolation: str = Extrapolation.FITTED,
) -> Path:
    """Write the light's far field as an IES LM-63-2019 file (type C photometry).

    Parameters
    ----------
    model : LightModel
        The light. Its far field ``Σ_s I_s(θ, φ)`` is tabulated at vertical angles
        γ = θ from 0 to ``vertical_max_deg`` (90 or 180; zero beyond 90°, behind the light
        plane) and horizontal angles C from 0 to 360°, ``C = (360° − φ) mod 360°``.
    path : path-like
        The ``.ies`` file to write.
    calibration : float, optional
        Candela per model unit. With it the file is absolute photometry (lumens/lamp
        ``-1``) in candela; without it the intensities are relative.
    lamp_lumens : float, optional
        Relative photometry scaled to this lamp flux: the intensities are scaled so that the
        table carries ``lamp_lumens``. Without it (and without ``calibration``) the
        intensities are scaled to a peak of 1000 and lumens/lamp is the table's own flux.
    vertical_step_deg, vertical_max_deg, horizontal_step_deg : float
        The angle grid, degrees; each step must divide its range.
    manufacturer, luminaire, lamp, lumcat, test, testlab, issue_date : str, optional
        Keywords ``[MANUFAC]``, ``[LUMINAIRE]``, ``[LAMP]`` (only when given), ``[LUMCAT]``,
        ``[TEST]``, ``[TESTLAB]``, ``[ISSUEDATE]``; the defaults come from the model's
        provenance and today's date.
    file_generation_type : str, optional
        A token of LM-63-2019 Table 2 (:data:`FILE_GENERATION_TYPES`). Default ``"1.01000"``
        (test at an unaccredited lab, interpolated angle set: the table is the fitted model
        resampled on a grid), or ``"1.01100"`` when ``lamp_lumens`` scales it.
    input_watts : float
        Input power, W (0 when unknown).
    extrapolation : {"fitted", "none"}
        Beyond each source's measured θ: the fits' extrapolation (the default), or zero
        (the measured range only). The file says which (``[_EXTRAPOLATION]``, ``[OTHER]``).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    ExportError
        One line naming the file and the field: a bad grid, a bad factor, a model with
        no flux, an unknown file generation type.

    Notes
    -----
    The keywords say what the numbers are: ``[_UNITS]`` ``candela`` or ``relative
    intensity``, ``[OTHER]`` the same in words with the calibration, and ``[FILEGENINFO]``
    how the table was made (fit methods, the θ range the measurement covered: beyond it
    the values are the fits' extrapolation or zero). User keywords give the table's
    photometric summary (:func:`processing.photometry.summarize`): ``[_MEASURED_THETA_MAX]``
    (degrees, every source measured up to it), ``[_EXTRAPOLATION]`` (``fitted`` or
    ``none``), ``[_FLUX_BEYOND_MEASURED]`` (% of the table's flux),
    ``[_BEAMANGLE_C0_C180]``, ``[_BEAMANGLE_C90_C270]``, ``[_FIELDANGLE_C0_C180]``,
    ``[_FIELDANGLE_C90_C270]`` (degrees) and ``[_PEAKDIRECTION]``.
    """
    path = Path(path)
    gamma, c = _ies_angles(path, vertical_step_deg, vertical_max_deg, horizontal_step_deg)
    extrapolation = checked_extrapolation(path, extrapolation)
    summary = summarize(model, extrapolation, near_field_m=None)
    table = far_field_table(model, gamma, c, extrapolation)
    factor, lamp_flux, absolute = far_field_scaling(path, summary.total_flux, table, calibration, lamp_lumens)
    file_generation_type = _ies_file_generation_type(path, file_generation_type, lamp_lumens)
    given = {
        "TEST": test,
        "TESTLAB": testlab,
        "ISSUEDATE": issue_date,
        "LUMCAT": lumcat,
        "LUMINAIRE": luminaire,
        "LAMP": lamp,
    }
    grid = f"{vertical_step_deg:g} x {horizontal_step_deg:g} degree grid"
    units = _ies_units(model, absolute, calibration, lamp_lumens)
    lines = ["IES:LM-63-2019", *_ies_keywords(model, given, manufacturer, grid, units, summary)]
    lumens = "-1" if absolute else plain_number(lamp_flux)
    lines += _ies_photometry(model, gamma, c, table * factor, lumens, file_generation_type, input_watts)
    return write_text(path, lines, "\r\n")

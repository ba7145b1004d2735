"""EULUMDAT (.ldt) files: the far field in cd/klm."""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

from drivers.contracts.version import __version__
from processing.exports.far_field import (
    angle_grid,
    ascii_only,
    checked_extrapolation,
    describe_light,
    far_field_scaling,
    far_field_table,
    intensity_uncertainty,
    luminous_opening,
    plain_number,
    write_text,
)
from processing.lightmodel import LightModel
from processing.options import Extrapolation
from processing.photometry import Photometry, summarize


def _ldt_report_line(run: str, model: LightModel, summary: Photometry) -> str:
    """Line 8, the measurement report: the γ measured, what lies beyond, the intensities' median
    1σ there, and the run (78 characters: a long run id is cut, not the range)."""
    beyond = "zero" if summary.extrapolation == Extrapolation.NONE else "fitted"
    median, _ = intensity_uncertainty(model, summary.light_theta_max_deg[0])
    return (
        f"to gamma {summary.light_theta_max_deg[0]:.1f} deg, {beyond} beyond, 1-sigma {100 * median:.2f} %; "
        f"mirrorgonio run {run}"
    )


def _ldt_description(
    model: LightModel, file_name: str, absolute: bool, grid: tuple, names: tuple, summary: Photometry
) -> list[str]:
    """EULUMDAT lines 1-12: the company and the units, the type and symmetry indicators, the angle grid
    ``(Mc, Dc, Ng, Dg)``, the report, the luminaire's name and number, the file name and the date.

    ``names`` is ``(company, luminaire, luminaire_number)``, the arguments of :func:`write_ldt`."""
    company, luminaire, luminaire_number = names
    n_c, c_step_deg, n_gamma, gamma_step_deg = grid
    symmetric = all(s.fit.method != "gaussian-2d" for s in model.sources)
    run, rig, methods = describe_light(model)
    scale = model.photometry.get("absolute")
    units = "candela (calibrated)" if absolute else f"relative ({model.units}, uncalibrated)"
    if absolute and scale is not None:
        units = f"candela (calibrated, 1-sigma {100 * scale['relative_uncertainty']:.2f} %)"

    def line(text: str, limit: int) -> str:
        return ascii_only(text)[:limit]

    return [
        line(f"{company} - far field, {units}", 78),
        "1" if symmetric else "3",  # Ityp: point source, symmetric about the vertical axis or not
        "0",  # Isym: every C-plane is stored
        str(n_c),  # Mc
        plain_number(c_step_deg),  # Dc
        str(n_gamma),  # Ng
        plain_number(gamma_step_deg),  # Dg
        line(_ldt_report_line(run, model, summary), 78),  # measurement report
        line(luminaire or f"near-field light model, {len(model.sources)} sources ({methods})", 78),
        line(luminaire_number or run, 78),
        line(file_name, 8 + 4 + 66),
        line(f"{_dt.date.today().isoformat()} / mirrorgonio {__version__} / rig {rig}", 78),
    ]


def _ldt_luminaire_and_lamps(
    model: LightModel, absolute: bool, lamp_flux: float, summary: Photometry, lamp: str | None
) -> list[str]:
    """EULUMDAT lines 13-26f: the luminaire's and luminous area's sizes, the ratios, and the lamps."""
    length, width = (1000.0 * x for x in luminous_opening(model))
    lines = [plain_number(length), plain_number(width), "0"]  # the luminaire's length, width and height (mm)
    lines += [
        plain_number(length),
        plain_number(width),
        "0",
        "0",
        "0",
        "0",
    ]  # the luminous area's, its heights at C0, C90, C180, C270
    dff = plain_number(summary.record()["downward_flux_percent"], 4)
    lines += [dff, "100", "1", "0"]  # DFF, LORL (%), conversion factor of the intensities, tilt in the measurement
    lamp_type = "mirrorgonio (candela)" if absolute else "mirrorgonio (relative)"  # 24 characters at most
    if lamp:
        lamp_type = ascii_only(lamp)[:24]
    # One standard set of one lamp: its type, total luminous flux (relative units unless calibrated), colour
    # appearance (the CCT, 16 characters at most), colour rendering (6 at most: not measured), wattage
    # including ballast.
    cct = model.chromaticity.get("cct_k")
    appearance = f"{cct:.0f}K" if cct is not None else ""
    rendering = "n/a" if model.chromaticity else ""
    return lines + ["1", "1", lamp_type, plain_number(lamp_flux), appearance, rendering, "0"]


def write_ldt(
    model: LightModel,
    path: str | os.PathLike[str],
    *,
    calibration: float | None = None,
    lamp_lumens: float | None = None,
    c_step_deg: float = 15.0,
    gamma_step_deg: float = 5.0,
    company: str = "mirrorgonio",
    luminaire: str | None = None,
    luminaire_number: str | None = None,
    extrapolation: str = Extrapolation.FITTED,
    lamp: str | None = None,
) -> Path:
    """Write the light's far field as an EULUMDAT (``.ldt``) file.

    Parameters
    ----------
    model : LightModel
        The light; its far field is tabulated at γ = 0..180° (zero beyond 90°) and C-planes
        ``0, c_step, …, 360° − c_step`` with ``C = (360° − φ) mod 360°``.
    path : path-like
        The ``.ldt`` file to write.
    calibration, lamp_lumens : float, optional
        As in :func:`write_ies`: candela per model unit, or a lamp flux to scale the
        relative intensities to. EULUMDAT stores cd/klm of the lamp flux, so the shape of
        the table does not depend on them, only the lamp flux (line 26c) does.
    c_step_deg, gamma_step_deg : float
        The angle grid, degrees.
    company, luminaire, luminaire_number : str, optional
        Identification lines 1, 9 and 10.
    extrapolation : {"fitted", "none"}
        Beyond each source's measured θ: the fits' extrapolation (the default), or zero.
        Line 8 (the measurement report) says which, with the measured θ.
    lamp : str, optional
        The lamp type (line 26b, its first 24 characters); default ``mirrorgonio (relative)``
        or ``mirrorgonio (candela)``.

    Returns
    -------
    Path
        The file written.

    Notes
    -----
    Every C-plane is stored (Isym 0): readers differ on how many C angles a file with Isym 1
    lists, and a full table reads the same everywhere. The type indicator says whether the
    far field is rotationally symmetric (Ityp 1: every source has a 1-D fit) or not
    (Ityp 3). The downward flux fraction and the light output ratio are 100 % (everything
    leaves the front of the plane, the model is the light itself). The direct ratios (line 24,
    room indices 0.6 … 5) are :func:`processing.photometry.direct_ratios`: the share of the
    flux falling directly on the work plane of a square room with the luminaires spread evenly
    over its ceiling.
    """
    path = Path(path)
    c_all = angle_grid(path, "c_step_deg", c_step_deg, 360.0)[:-1]
    gamma = angle_grid(path, "gamma_step_deg", gamma_step_deg, 180.0)
    extrapolation = checked_extrapolation(path, extrapolation)
    summary = summarize(model, extrapolation, near_field_m=None)
    table = far_field_table(model, gamma, c_all, extrapolation)
    factor, lamp_flux, absolute = far_field_scaling(path, summary.total_flux, table, calibration, lamp_lumens)
    grid = (len(c_all), c_step_deg, len(gamma), gamma_step_deg)
    lines = _ldt_description(model, path.name, absolute, grid, (company, luminaire, luminaire_number), summary)
    lines += _ldt_luminaire_and_lamps(model, absolute, lamp_flux, summary, lamp)
    lines += [f"{v:.4f}" for v in summary.direct_ratios]  # direct ratios for the room indices 0.6 … 5
    lines += [plain_number(v) for v in c_all]
    lines += [plain_number(v) for v in gamma]
    cd_per_klm = table * factor * 1000.0 / lamp_flux
    lines += [plain_number(v) for v in cd_per_klm.ravel()]
    return write_text(path, lines, "\r\n")

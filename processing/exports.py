"""Exports of a light model to the formats lighting software reads.

- :func:`write_ies` — IES LM-63-2019 photometric file, type C photometry: the **far field**
  of the whole light, ``Σ_s I_s(θ, φ)``.
- :func:`write_ldt` — EULUMDAT (``.ldt``), the same far field in cd/klm.
- :func:`write_tm25` / :func:`read_tm25` — IES TM-25-13 binary ray files: the **near
  field**, rays leaving each source's emitting disc with directions drawn from its own
  ``I_s(θ, φ)``.

Angles (both far-field formats): the light's axis (+z of the light frame) is photometric
nadir, vertical angle γ = θ; horizontal angle C = 0 is the light frame's +x, and C grows
counter-clockwise seen from above the luminaire hanging light-down (LM-63, type C), which
is towards the light's −y: ``C = (360° − φ) mod 360°``. The luminous opening's length runs
along C0–C180 (light x), its width along C90–C270 (light y).

Units: a light model is relative unless its run was calibrated, and even then it is
radiometric (W/sr). A far-field file therefore holds **relative intensities** unless a
``calibration`` factor (candela per model unit) is given; the file says which in its
keywords. Relative files follow the formats' relative photometry: intensities scaled to a
peak of 1000, with the lamp flux set to the flux of that same table (or to ``lamp_lumens``
when given, the intensities then scaled so the table carries exactly that flux).

Facts of the formats relied on (``docs/light-model.md`` cites them):
LM-63-2019 line 1 ``IES:LM-63-2019``, keywords ``[TEST] [TESTLAB] [ISSUEDATE] [MANUFAC]``
required, ``TILT=NONE``, then ``#lamps lumens/lamp multiplier #vertical #horizontal
photometric-type(1 = C) units-type(2 = metres) width length height``, then ``ballast-factor
file-generation-type input-watts``; the file generation type is a Table 2 token
(``1.00000`` test at an unaccredited lab, ``1.01000`` … with interpolated angle set,
``1.01100`` … interpolated and lumen scaled, ``1.00010`` computer simulation, ``1.00001``
undefined); lumens/lamp ``-1`` means absolute photometry. TM-25-13: little-endian, "TM25",
i32 2013, fluxes f32 at 12 and 16, u64 ray count at 20, eight i32 column flags at 256, nine
4000-byte UTF-32LE text fields from 288, spectral tables from 36288 zero-padded to a
multiple of 32 bytes, then 512-byte column labels and the additional text, then the rays
as float32 rows ``x y z kx ky kz`` (mm, unit vector) followed by the flagged columns.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from drivers.contracts.version import __version__
from processing.lightmodel import LightModel, SourceModel

__all__ = [
    "ExportError",
    "FILE_GENERATION_TYPES",
    "TM25Error",
    "TM25_COLUMNS",
    "read_tm25",
    "write_ies",
    "write_ldt",
    "write_tm25",
]


class ExportError(ValueError):
    """An export that cannot be written (one line naming the file and the field)."""


class TM25Error(ExportError):
    """An unreadable or malformed TM-25 ray file (one line naming the file and the field)."""


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


def _num(x: float, digits: int = 6) -> str:
    """A number in plain positional notation (no exponent), ``digits`` significant digits."""
    x = float(x)
    if x == 0 or not math.isfinite(x):
        return "0"
    return np.format_float_positional(x, precision=digits, unique=False, fractional=False, trim="-")


def _grid(path: Path, name: str, step: float, stop: float) -> np.ndarray:
    if not (step > 0 and math.isfinite(step)):
        raise ExportError(f"{path}: {name}: must be a positive number of degrees, got {step!r}")
    n = stop / step
    if abs(n - round(n)) > 1e-9:
        raise ExportError(f"{path}: {name}: {step:g}° does not divide {stop:g}°")
    return np.linspace(0.0, stop, int(round(n)) + 1)


def _far_field_table(model: LightModel, gamma_deg: np.ndarray, c_deg: np.ndarray) -> np.ndarray:
    """``Σ_s I_s`` on a (C, γ) grid, shape ``(len(c), len(gamma))``, in model units."""
    theta = np.radians(np.asarray(gamma_deg, dtype=float))[None, :]
    phi = np.radians(np.mod(-np.asarray(c_deg, dtype=float), 360.0))[:, None]
    return model.far_field(theta, phi)


def _scaling(
    path: Path, model: LightModel, table: np.ndarray, calibration: float | None, lamp_lumens: float | None
) -> tuple[float, float, bool]:
    """``(factor, lamp_flux, absolute)``: what multiplies the model's intensities, and the lamp flux."""
    if calibration is not None and lamp_lumens is not None:
        raise ExportError(
            f"{path}: give calibration (absolute candela) or lamp_lumens (relative, lumen scaled), not both"
        )
    flux = model.total_flux()
    if not (flux > 0) or not np.any(table > 0):
        raise ExportError(f"{path}: the light model emits no flux in front of its plane")
    if calibration is not None:
        calibration = float(calibration)
        if not (calibration > 0 and math.isfinite(calibration)):
            raise ExportError(
                f"{path}: calibration: must be a positive factor (cd per model unit), got {calibration!r}"
            )
        return calibration, calibration * flux, True
    if lamp_lumens is not None:
        lamp_lumens = float(lamp_lumens)
        if not (lamp_lumens > 0 and math.isfinite(lamp_lumens)):
            raise ExportError(f"{path}: lamp_lumens: must be a positive number of lumens, got {lamp_lumens!r}")
        return lamp_lumens / flux, lamp_lumens, False
    factor = 1000.0 / float(np.max(table))
    return factor, factor * flux, False


def _opening(model: LightModel) -> tuple[float, float]:
    """``(length along light x, width along light y)`` of the sources' discs, metres."""
    u = np.array([s.centre_m[0] for s in model.sources])
    v = np.array([s.centre_m[1] for s in model.sources])
    r = np.array([s.radius_m for s in model.sources])
    return float(np.max(u + r) - np.min(u - r)), float(np.max(v + r) - np.min(v - r))


def _theta_cover(model: LightModel) -> tuple[float, float]:
    lo = min(s.fit.theta_range[0] for s in model.sources)
    hi = max(s.fit.theta_range[1] for s in model.sources)
    return math.degrees(lo), math.degrees(hi)


def _write_text(path: Path, lines: list[str], newline: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="ascii", errors="replace", newline="") as f:
        f.write(newline.join(lines) + newline)
    os.replace(tmp, path)
    return path


def _wrap_numbers(values: Iterable[str], per_line: int = 10) -> list[str]:
    values = list(values)
    return [" ".join(values[i : i + per_line]) for i in range(0, len(values), per_line)] or [""]


def _ascii(text: str) -> str:
    return "".join(c if 32 <= ord(c) < 127 else "?" for c in str(text))


def _keyword(name: str, text: str, width: int = 132) -> list[str]:
    """``[NAME] text``, continued on ``[MORE]`` lines so that no line passes ``width`` characters."""
    text = " ".join(_ascii(text).split())
    head, lines = f"[{name}] ", []
    while True:
        room = width - len(head)
        if len(text) <= room:
            lines.append((head + text).rstrip())
            return lines
        cut = text.rfind(" ", 0, room)
        cut = room if cut <= 0 else cut
        lines.append(head + text[:cut].rstrip())
        text, head = text[cut:].lstrip(), "[MORE] "


def _describe(model: LightModel) -> tuple[str, str, str]:
    prov = model.provenance
    run = str(prov.get("run_id") or "unknown run")
    rig = str(prov.get("rig") or "unknown rig")
    methods = sorted({s.fit.method for s in model.sources})
    return run, rig, ", ".join(methods)


def _ies_angles(
    path: Path, vertical_step_deg: float, vertical_max_deg: float, horizontal_step_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """The vertical angles γ (to 90° or 180°, type C) and the horizontal angles C (to 360°), degrees."""
    if vertical_max_deg not in (90, 180):
        raise ExportError(f"{path}: vertical_max_deg: must be 90 or 180 (type C), got {vertical_max_deg!r}")
    gamma = _grid(path, "vertical_step_deg", vertical_step_deg, float(vertical_max_deg))
    return gamma, _grid(path, "horizontal_step_deg", horizontal_step_deg, 360.0)


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
        return "candela", (
            f"Absolute photometry: candela = {calibration:.6g} cd per model unit x the model's {model.units} "
            "intensities."
        )
    scaled = f"scaled to a lamp flux of {lamp_lumens:.6g} lm" if lamp_lumens is not None else "scaled to a peak of 1000"
    return "relative intensity", (
        f"Relative intensity, not candela: the light model is {model.units} and uncalibrated "
        f"photometrically; values {scaled}, lumens per lamp is the flux of this table."
    )


def _ies_keywords(model: LightModel, given: dict, manufacturer: str, grid: str, units: tuple[str, str]) -> list[str]:
    """The keyword lines: the test and the luminaire (``given``, else from the model's provenance), how
    the table was made, and what its numbers are."""
    run, rig, methods = _describe(model)
    lo, hi = _theta_cover(model)
    today = _dt.date.today().isoformat()
    units_word, other = units
    lines = _keyword("TEST", given["TEST"] or f"mirrorgonio run {run}")
    lines += _keyword("TESTLAB", given["TESTLAB"] or f"mirrorgonio mirror-ball goniophotometer, rig {rig}")
    lines += _keyword("ISSUEDATE", given["ISSUEDATE"] or today)
    lines += _keyword("MANUFAC", manufacturer)
    lines += _keyword("LUMCAT", given["LUMCAT"] or run)
    lines += _keyword(
        "LUMINAIRE", given["LUMINAIRE"] or f"near-field light model of {len(model.sources)} point sources"
    )
    lines += _keyword(
        "FILEGENINFO",
        f"Far field (sum of the sources' intensities) of a light model fitted ({methods}) to a mirror-ball "
        f"goniophotometer measurement, resampled on a {grid}. "
        f"The measurement covered vertical angles {lo:.1f} to {hi:.1f} degrees; values outside are extrapolated "
        f"from the fits. Generated by mirrorgonio {__version__} on {today}.",
    )
    lines += _keyword("OTHER", other)
    lines += _keyword("_UNITS", units_word)
    return lines + _keyword("_SOFTWARE", f"mirrorgonio {__version__}")


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
    length, width = _opening(model)
    lines = ["TILT=NONE", f"1 {lumens} 1 {len(gamma)} {len(c)} 1 2 {_num(width)} {_num(length)} 0"]
    lines.append(f"1.0 {file_generation_type} {_num(input_watts)}")
    lines += _wrap_numbers(_num(g) for g in gamma)
    lines += _wrap_numbers(_num(h) for h in c)
    for row in intensities:
        lines += _wrap_numbers(_num(v) for v in row)
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
    lumcat: str | None = None,
    test: str | None = None,
    testlab: str | None = None,
    issue_date: str | None = None,
    file_generation_type: str | None = None,
    input_watts: float = 0.0,
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
    manufacturer, luminaire, lumcat, test, testlab, issue_date : str, optional
        Keywords ``[MANUFAC]``, ``[LUMINAIRE]``, ``[LUMCAT]``, ``[TEST]``, ``[TESTLAB]``,
        ``[ISSUEDATE]``; the defaults come from the model's provenance and today's date.
    file_generation_type : str, optional
        A token of LM-63-2019 Table 2 (:data:`FILE_GENERATION_TYPES`). Default ``"1.01000"``
        (test at an unaccredited lab, interpolated angle set: the table is the fitted model
        resampled on a grid), or ``"1.01100"`` when ``lamp_lumens`` scales it.
    input_watts : float
        Input power, W (0 when unknown).

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
    how the table was made (fit methods, the θ range the measurement covered: outside it
    the values are extrapolations of the fits).
    """
    path = Path(path)
    gamma, c = _ies_angles(path, vertical_step_deg, vertical_max_deg, horizontal_step_deg)
    table = _far_field_table(model, gamma, c)
    factor, lamp_flux, absolute = _scaling(path, model, table, calibration, lamp_lumens)
    file_generation_type = _ies_file_generation_type(path, file_generation_type, lamp_lumens)
    given = {"TEST": test, "TESTLAB": testlab, "ISSUEDATE": issue_date, "LUMCAT": lumcat, "LUMINAIRE": luminaire}
    grid = f"{vertical_step_deg:g} x {horizontal_step_deg:g} degree grid"
    units = _ies_units(model, absolute, calibration, lamp_lumens)
    lines = ["IES:LM-63-2019", *_ies_keywords(model, given, manufacturer, grid, units)]
    lumens = "-1" if absolute else _num(lamp_flux)
    lines += _ies_photometry(model, gamma, c, table * factor, lumens, file_generation_type, input_watts)
    return _write_text(path, lines, "\r\n")


def _ldt_description(model: LightModel, file_name: str, absolute: bool, grid: tuple, names: tuple) -> list[str]:
    """EULUMDAT lines 1-12: the company and the units, the type and symmetry indicators, the angle grid
    ``(Mc, Dc, Ng, Dg)``, the report, the luminaire's name and number, the file name and the date.

    ``names`` is ``(company, luminaire, luminaire_number)``, the arguments of :func:`write_ldt`."""
    company, luminaire, luminaire_number = names
    n_c, c_step_deg, n_gamma, gamma_step_deg = grid
    symmetric = all(s.fit.method != "gaussian-2d" for s in model.sources)
    run, rig, methods = _describe(model)
    units = "candela (calibrated)" if absolute else f"relative ({model.units}, uncalibrated)"

    def line(text: str, limit: int) -> str:
        return _ascii(text)[:limit]

    return [
        line(f"{company} - far field, {units}", 78),
        "1" if symmetric else "3",  # Ityp: point source, symmetric about the vertical axis or not
        "0",  # Isym: every C-plane is stored
        str(n_c),  # Mc
        _num(c_step_deg),  # Dc
        str(n_gamma),  # Ng
        _num(gamma_step_deg),  # Dg
        line(f"mirrorgonio run {run}", 78),  # measurement report
        line(luminaire or f"near-field light model, {len(model.sources)} sources ({methods})", 78),
        line(luminaire_number or run, 78),
        line(file_name, 8 + 4 + 66),
        line(f"{_dt.date.today().isoformat()} / mirrorgonio {__version__} / rig {rig}", 78),
    ]


def _ldt_luminaire_and_lamps(model: LightModel, absolute: bool, lamp_flux: float) -> list[str]:
    """EULUMDAT lines 13-26f: the luminaire's and luminous area's sizes, the ratios, and the lamps."""
    length, width = (1000.0 * x for x in _opening(model))
    lines = [_num(length), _num(width), "0"]  # the luminaire's length, width and height (mm)
    lines += [_num(length), _num(width), "0", "0", "0", "0"]  # the luminous area's, its heights at C0, C90, C180, C270
    lines += ["100", "100", "1", "0"]  # DFF, LORL (%), conversion factor of the intensities, tilt in the measurement
    lamp_type = "mirrorgonio (candela)" if absolute else "mirrorgonio (relative)"  # 24 characters at most
    # One standard set of one lamp: its type, total luminous flux (relative units unless calibrated), colour
    # appearance, colour rendering, wattage including ballast.
    return lines + ["1", "1", lamp_type, _num(lamp_flux), "", "", "0"]


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
    leaves the front of the plane, the model is the light itself); the direct ratios
    (utilisation factors for standard rooms) are not computed and are written as zero.
    """
    path = Path(path)
    c_all = _grid(path, "c_step_deg", c_step_deg, 360.0)[:-1]
    gamma = _grid(path, "gamma_step_deg", gamma_step_deg, 180.0)
    table = _far_field_table(model, gamma, c_all)
    factor, lamp_flux, absolute = _scaling(path, model, table, calibration, lamp_lumens)
    grid = (len(c_all), c_step_deg, len(gamma), gamma_step_deg)
    lines = _ldt_description(model, path.name, absolute, grid, (company, luminaire, luminaire_number))
    lines += _ldt_luminaire_and_lamps(model, absolute, lamp_flux)
    lines += ["0"] * 10  # direct ratios, not computed
    lines += [_num(v) for v in c_all]
    lines += [_num(v) for v in gamma]
    cd_per_klm = table * factor * 1000.0 / lamp_flux
    lines += [_num(v) for v in cd_per_klm.ravel()]
    return _write_text(path, lines, "\r\n")


# --------------------------------------------------------------------------- TM-25-13
_FLAG_COLUMNS = {
    "position": ("x", "y", "z"),
    "direction": ("kx", "ky", "kz"),
    "radiant_flux": ("phi",),
    "wavelength": ("lambda",),
    "luminous_flux": ("Tri_Y",),
    "stokes": ("S1", "S2", "S3", "PolEllipseX", "PolEllipseY", "PolEllipseZ"),
    "tristimulus": ("Tri_X", "Tri_Z"),
    "spectrum_index": ("spectrumIdx",),
}
"""The eight column flags in file order (4.7.2), each with the ray columns it adds."""
_FLAG_NAMES = tuple(_FLAG_COLUMNS)
TM25_COLUMNS = tuple(column for columns in _FLAG_COLUMNS.values() for column in columns)
"""The standard ray columns in file order (``phi`` radiant flux W, ``Tri_Y`` luminous flux lm)."""
_TEXT_FIELDS = (
    "name",
    "manufacturer",
    "model_creator",
    "rayfile_creator",
    "equipment",
    "camera",
    "light_source_operation",
    "additional_info",
    "data_reference",
)
_HEADER = struct.Struct("<4siiffQ28siifffiii168x")  # 4.7.1, 256 bytes
_TEXT_START, _TEXT_BYTES, _SPECTRA_START = 288, 4000, 36288
assert _HEADER.size == 256


def _utf32(text: str, nbytes: int) -> bytes:
    raw = str(text).encode("utf-32-le")[: nbytes - 4]  # keep a terminating zero
    return raw + b"\0" * (nbytes - len(raw))


def _from_utf32(raw: bytes) -> str:
    text = raw.decode("utf-32-le", errors="replace")
    return text.split("\0", 1)[0]


def _sample_directions(
    source: SourceModel, n: int, rng: np.random.Generator, n_theta: int = 2048, n_phi: int = 256
) -> np.ndarray:
    """``n`` unit vectors drawn with density ∝ ``I_s(θ, φ)`` over the hemisphere.

    The intensity is tabulated on cells of equal Δθ (and Δφ for 2-D fits); a cell is drawn with probability ∝ its
    flux ``I(θ_mid, φ_mid)·Δcosθ·Δφ``, then a direction uniformly in solid angle within it (uniform in cos θ and φ):
    the exact sampling of the piecewise-constant intensity."""
    edges = np.linspace(0.0, 0.5 * math.pi, n_theta + 1)
    mids = 0.5 * (edges[:-1] + edges[1:])
    dcos = np.cos(edges[:-1]) - np.cos(edges[1:])
    n_p = n_phi if source.fit.method == "gaussian-2d" else 1
    phi_edges = np.linspace(0.0, 2.0 * math.pi, n_p + 1)
    phi_mids = 0.5 * (phi_edges[:-1] + phi_edges[1:])
    weight = source.intensity(mids[:, None], phi_mids[None, :]) * dcos[:, None]
    cdf = np.cumsum(weight.ravel())
    if not cdf[-1] > 0:
        raise ExportError(f"source {source.name!r}: emits nothing to sample")
    cell = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), cdf.size - 1)
    i, j = np.divmod(cell, n_p)
    cos_t = np.cos(edges[i]) - rng.random(n) * dcos[i]
    phi = phi_edges[j] + rng.random(n) * (phi_edges[j + 1] - phi_edges[j])
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t**2))
    return np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])


def _allocate(fluxes: np.ndarray, n_rays: int) -> np.ndarray:
    """Rays per source ∝ flux (largest remainder), at least one for every emitting source."""
    emitting = fluxes > 0
    counts = np.zeros(len(fluxes), dtype=np.int64)
    counts[emitting] = 1
    rest = n_rays - int(counts.sum())
    share = fluxes / fluxes.sum() * rest
    counts += np.floor(share).astype(np.int64)
    remainder = n_rays - int(counts.sum())
    order = np.argsort(-(share - np.floor(share)), kind="stable")
    counts[order[:remainder]] += 1
    return counts


def _emitting_fluxes(path: Path, model: LightModel, n_rays: int) -> np.ndarray:
    """The sources' fluxes ``∫ I_s dΩ``, for a light that emits and has a ray for each emitting source."""
    fluxes = np.array([s.flux() for s in model.sources])
    if not np.all(np.isfinite(fluxes)) or not fluxes.sum() > 0:
        raise ExportError(f"{path}: the light model emits no flux in front of its plane")
    if n_rays < int(np.count_nonzero(fluxes > 0)):
        raise ExportError(
            f"{path}: n_rays: {n_rays} is fewer than the {int(np.count_nonzero(fluxes > 0))} emitting sources"
        )
    return fluxes


def _sample_rays(model: LightModel, fluxes: np.ndarray, n_rays: int, rng: np.random.Generator) -> np.ndarray:
    """``(n_rays, 7)`` rays ``x y z kx ky kz phi``, source after source: a share of the rays ∝ the source's
    flux, starting uniformly on its disc (mm, z = 0), directions drawn from its intensity, each carrying
    ``Φ_s / n_s``."""
    counts = _allocate(fluxes, n_rays)
    rays = np.empty((n_rays, 7), dtype=np.float64)
    row = 0
    for s, flux, k in zip(model.sources, fluxes, counts, strict=True):
        if k == 0:
            continue
        r = s.radius_m * np.sqrt(rng.random(k))
        a = rng.random(k) * 2.0 * math.pi
        rays[row : row + k, 0] = 1000.0 * (s.centre_m[0] + r * np.cos(a))
        rays[row : row + k, 1] = 1000.0 * (s.centre_m[1] + r * np.sin(a))
        rays[row : row + k, 2] = 0.0
        rays[row : row + k, 3:6] = _sample_directions(s, int(k), rng)
        rays[row : row + k, 6] = flux / k
        row += k
    return rays


def _tm25_texts(model: LightModel, name: str | None, manufacturer: str, seed: int) -> dict[str, str]:
    """The nine text fields (4.7.3) by name: the light, who made the model and the file, and how."""
    prov = model.provenance
    run = str(prov.get("run_id") or "unknown run")
    unit_note = "W (radiant flux)" if model.units == "W/sr" else "relative units (uncalibrated measurement)"
    return {
        "name": name or f"light of mirrorgonio run {run}",
        "manufacturer": manufacturer,
        "model_creator": f"mirrorgonio {__version__} ({prov.get('method', 'unknown method')})",
        "rayfile_creator": f"mirrorgonio {__version__}",
        "equipment": f"mirror-ball goniophotometer, rig {prov.get('rig') or 'unknown'}",
        "camera": str(prov.get("camera") or ""),
        "light_source_operation": str(prov.get("operation") or ""),
        "additional_info": (
            f"Rays sampled (seed {seed}) from a near-field model of {len(model.sources)} point sources "
            f"on emitting discs; ray flux column phi in {unit_note}; positions in mm in the light "
            f"frame (emission towards +z)."
        ),
        "data_reference": f"run {run}, file {prov.get('run_file') or 'unknown'}",
    }


def _tm25_header_and_flags(creation_method: int, radiant_flux: float, n_rays: int) -> bytes:
    """The header (4.7.1) with the current date and time, no luminous flux (NaN) and no spectrum, then the column
    flags (4.7.2): position, direction and radiant flux."""
    now = _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().encode("ascii")[:28]
    nan = float("nan")
    # File type, version, creation method, luminous and radiant flux, rays, date and time, start position,
    # spectrum type, wavelength and its range, spectral tables, additional columns, additional text (bytes).
    header = _HEADER.pack(b"TM25", 2013, creation_method, nan, radiant_flux, n_rays, now, 0, 0, nan, nan, nan, 0, 0, 0)
    return header + struct.pack("<8i", 1, 1, 1, 0, 0, 0, 0, 0)


def write_tm25(
    model: LightModel,
    path: str | os.PathLike[str],
    n_rays: int,
    *,
    seed: int,
    name: str | None = None,
    manufacturer: str = "unknown",
    creation_method: int = 1,
) -> Path:
    """Write the light's near field as an IES TM-25-13 binary ray file.

    Rays are sampled from the near-field model: each source gets a share of ``n_rays``
    proportional to its flux ``∫ I_s dΩ``; a ray starts uniformly on the source's emitting
    disc (radius ``radius_m`` about ``(u_s, v_s, 0)``), leaves in a direction drawn with
    density ∝ ``I_s(θ, φ)``, and carries the flux ``Φ_s / n_s`` so that the rays add up to
    the model's total flux.

    Parameters
    ----------
    model : LightModel
        The light.
    path : path-like
        The ``.tm25ray`` file to write.
    n_rays : int
        Number of rays (at least the number of emitting sources).
    seed : int
        Seed of the random generator: the same seed writes the same file.
    name, manufacturer : str, optional
        Text fields 4.7.3.1 and 4.7.3.2.
    creation_method : int
        4.7.1.3: 1 measurement (default: the model is measured), 0 simulation.

    Returns
    -------
    Path
        The file written.

    Notes
    -----
    Positions are millimetres in the light frame (the plane at z = 0, emission towards +z);
    the flux column is radiant flux (``phi``, flag 4.7.2.3) in the model's units × sr: W
    when the model is W/sr, relative otherwise (text field 4.7.3.8 says which). The header's
    luminous flux is NaN (not given), the spectrum type 0 (none).
    """
    path = Path(path)
    if isinstance(n_rays, bool) or not isinstance(n_rays, (int, np.integer)) or n_rays < 1:
        raise ExportError(f"{path}: n_rays: must be a positive integer, got {n_rays!r}")
    if creation_method not in (0, 1):
        raise ExportError(
            f"{path}: creation_method: must be 0 (simulation) or 1 (measurement), got {creation_method!r}"
        )
    fluxes = _emitting_fluxes(path, model, n_rays)
    rays32 = _sample_rays(model, fluxes, int(n_rays), np.random.default_rng(seed)).astype("<f4")
    total = float(np.sum(rays32[:, 6], dtype=np.float64))
    texts = _tm25_texts(model, name, manufacturer, seed)
    head = _tm25_header_and_flags(int(creation_method), total, int(n_rays))
    text = b"".join(_utf32(texts[k], _TEXT_BYTES) for k in _TEXT_FIELDS)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(head + text)  # no spectral tables, column labels or additional text
        f.write(rays32.tobytes())
    os.replace(tmp, path)
    return path


def _read_tm25_flags(path: Path, head: bytes) -> dict[str, bool]:
    """The eight column flags (4.7.2) by name; position, direction and a flux must be there."""
    flag_values = struct.unpack_from("<8i", head, 256)
    flags = {}
    for name, value in zip(_FLAG_NAMES, flag_values, strict=True):
        if value not in (0, 1):
            raise TM25Error(f"{path}: {name} flag: {value}, must be 0 or 1")
        flags[name] = bool(value)
    if not (flags["position"] and flags["direction"]):
        raise TM25Error(f"{path}: position and direction flags must be 1, are {flag_values[0]} and {flag_values[1]}")
    if not (flags["radiant_flux"] or flags["luminous_flux"]):
        raise TM25Error(f"{path}: neither the radiant nor the luminous flux flag is set")
    return flags


def _read_tm25_header(path: Path, head: bytes) -> tuple[dict[str, Any], tuple[int, int, int]]:
    """The header (4.7.1), the column flags and the text fields (4.7.3) from the file's first bytes, checked;
    also the counts of what follows them: spectral tables, additional columns, bytes of additional text."""
    if len(head) < _SPECTRA_START:
        raise TM25Error(f"{path}: {len(head)} bytes, shorter than a TM-25 header ({_SPECTRA_START} bytes)")
    magic, version, method, lum, rad, n_rays, date, start, spectrum, lam, lam_min, lam_max, *counts = (
        _HEADER.unpack_from(head, 0)
    )
    if magic != b"TM25":
        raise TM25Error(f"{path}: not a TM-25 ray file (file type {magic!r}, expected b'TM25')")
    if version != 2013:
        raise TM25Error(f"{path}: file version: {version}, this reader knows TM-25-13 (2013)")
    flags = _read_tm25_flags(path, head)
    n_spectra, n_addtl, addtl_text = counts
    if n_spectra < 0 or n_addtl < 0 or addtl_text < 0 or addtl_text % 4:
        raise TM25Error(
            f"{path}: header: negative counts or a text size that is not whole characters "
            f"(spectra {n_spectra}, items {n_addtl}, text {addtl_text} bytes)"
        )
    header = {
        "format": "TM25",
        "version": version,
        "creation_method": method,
        "luminous_flux": lum,
        "radiant_flux": rad,
        "n_rays": n_rays,
        "date_time": date.split(b"\0", 1)[0].decode("ascii", errors="replace"),
        "start_position": start,
        "spectrum_type": spectrum,
        "wavelength": lam,
        "wavelength_min": lam_min,
        "wavelength_max": lam_max,
        "flags": flags,
        "texts": {
            k: _from_utf32(head[_TEXT_START + i * _TEXT_BYTES : _TEXT_START + (i + 1) * _TEXT_BYTES])
            for i, k in enumerate(_TEXT_FIELDS)
        },
    }
    return header, (n_spectra, n_addtl, addtl_text)


def _read_tm25_spectra(path: Path, f: BinaryIO, n_spectra: int) -> list[dict[str, np.ndarray]]:
    """The spectral tables (wavelength, weight pairs) and their zero padding to a multiple of 32 bytes."""
    spectra, nbytes = [], 0
    for i in range(n_spectra):
        raw = f.read(4)
        if len(raw) < 4:
            raise TM25Error(f"{path}: spectral table {i + 1}: file ends in it")
        (m,) = struct.unpack("<i", raw)
        if m <= 0:
            raise TM25Error(f"{path}: spectral table {i + 1}: {m} entries")
        pairs = np.frombuffer(f.read(8 * m), dtype="<f4")
        if pairs.size < 2 * m:
            raise TM25Error(f"{path}: spectral table {i + 1}: file ends in it")
        spectra.append({"wavelength": pairs[0::2].copy(), "weight": pairs[1::2].copy()})
        nbytes += 4 + 8 * m
    f.read((-nbytes) % 32)
    return spectra


def read_tm25(path: str | os.PathLike[str]) -> tuple[dict[str, Any], np.ndarray]:
    """Read an IES TM-25-13 binary ray file.

    Parameters
    ----------
    path : path-like
        The ray file.

    Returns
    -------
    header : dict
        ``version``, ``creation_method`` (0 simulation, 1 measurement),
        ``luminous_flux`` (lm, NaN if not given), ``radiant_flux`` (W, NaN if not given),
        ``n_rays``, ``date_time``, ``start_position``, ``spectrum_type``, ``wavelength``,
        ``wavelength_min``, ``wavelength_max``, ``flags`` (the eight column flags by name),
        ``texts`` (the nine description fields by name), ``spectra`` (list of
        ``{"wavelength", "weight"}`` arrays), ``additional_columns``, ``additional_text``,
        ``columns`` (names of the ray array's columns, see :data:`TM25_COLUMNS`) and
        ``ray_offset`` (byte where the rays start).
    rays : ndarray (n_rays, n_columns) float32
        One row per ray, columns as ``header["columns"]``: position in mm, direction, then
        the flagged items (``phi`` radiant flux, ``Tri_Y`` luminous flux, …).

    Raises
    ------
    TM25Error
        One line naming the file and the field: not TM-25, another version, a bad flag,
        a truncated file.

    Notes
    -----
    The header's total flux and the sum of the rays' fluxes need not agree (real files
    exist where they do not); both are returned as they are.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            header, (n_spectra, n_addtl, addtl_text) = _read_tm25_header(path, f.read(_SPECTRA_START))
            header["spectra"] = _read_tm25_spectra(path, f, n_spectra)
            header["additional_columns"] = labels = [_from_utf32(f.read(512)) for _ in range(n_addtl)]
            header["additional_text"] = _from_utf32(f.read(addtl_text)) if addtl_text else ""
            offset = f.tell()
    except OSError as e:
        raise TM25Error(f"{path}: cannot read ({e.strerror or e})") from None
    flags, n_rays = header["flags"], header["n_rays"]
    columns = [c for flag in _FLAG_NAMES if flags[flag] for c in _FLAG_COLUMNS[flag]] + labels
    expected = offset + n_rays * len(columns) * 4
    if size < expected:
        raise TM25Error(f"{path}: {size} bytes, {n_rays} rays of {len(columns)} columns need {expected}: truncated")
    rays = np.fromfile(path, dtype="<f4", count=n_rays * len(columns), offset=offset).reshape(n_rays, len(columns))
    header.update(columns=columns, ray_offset=offset, trailing_bytes=size - expected)
    return header, rays

"""IES TM-25-13 binary ray files: the near field, rays leaving each source's emitting disc."""

from __future__ import annotations

import datetime as _dt
import math
import os
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from drivers.contracts.version import __version__
from processing.colour import describe
from processing.exports.far_field import ExportError, absolute_note, far_field_scaling
from processing.lightmodel import LightModel, SourceModel


class TM25Error(ExportError):
    """An unreadable or malformed TM-25 ray file (one line naming the file and the field)."""


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


_FLAG_NAMES = tuple(_FLAG_COLUMNS)


TM25_COLUMNS = tuple(column for columns in _FLAG_COLUMNS.values() for column in columns)


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


class _DirectionTable:
    """A source's intensity tabulated for drawing directions with density ∝ ``I_s(θ, φ)`` over
    the hemisphere.

    The intensity is tabulated on cells of equal Δθ (and Δφ for 2-D fits); a cell is drawn with probability ∝ its
    flux ``I(θ_mid, φ_mid)·Δcosθ·Δφ``, then a direction uniformly in solid angle within it (uniform in cos θ and φ):
    the exact sampling of the piecewise-constant intensity. Made once per source, drawn from block after block."""

    def __init__(self, source: SourceModel, n_theta: int = 2048, n_phi: int = 256) -> None:
        self.edges = np.linspace(0.0, 0.5 * math.pi, n_theta + 1)
        mids = 0.5 * (self.edges[:-1] + self.edges[1:])
        self.dcos = np.cos(self.edges[:-1]) - np.cos(self.edges[1:])
        self.n_p = n_phi if source.fit.method == "gaussian-2d" else 1
        self.phi_edges = np.linspace(0.0, 2.0 * math.pi, self.n_p + 1)
        phi_mids = 0.5 * (self.phi_edges[:-1] + self.phi_edges[1:])
        weight = source.intensity(mids[:, None], phi_mids[None, :]) * self.dcos[:, None]
        self.cdf = np.cumsum(weight.ravel())
        if not self.cdf[-1] > 0:
            raise ExportError(f"source {source.name!r}: emits nothing to sample")

    def draw(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` unit vectors, ``(n, 3)``."""
        cell = np.minimum(np.searchsorted(self.cdf, rng.random(n) * self.cdf[-1], side="right"), self.cdf.size - 1)
        i, j = np.divmod(cell, self.n_p)
        cos_t = np.cos(self.edges[i]) - rng.random(n) * self.dcos[i]
        phi = self.phi_edges[j] + rng.random(n) * (self.phi_edges[j + 1] - self.phi_edges[j])
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


#: Rays drawn and written at a time, whatever the file's number of rays: 2¹⁷, 7 MB of float64
#: rays, 3.7 MB as written, and some 12 MB of the draws' temporaries.
RAY_BLOCK = 1 << 17


def _ray_blocks(
    model: LightModel,
    fluxes: np.ndarray,
    n_rays: int,
    rng: np.random.Generator,
    colour: RayColour | None = None,
    block: int = RAY_BLOCK,
) -> Iterator[np.ndarray]:
    """The rays, ``(k, 7)`` float32 ``x y z kx ky kz phi`` at most ``block`` at a time, source after
    source: a share of the rays ∝ the source's flux, starting uniformly on its disc (mm, z = 0),
    directions drawn from its intensity, each carrying ``Φ_s / n_s``. With ``colour``, ``(k, 10)``:
    then ``Tri_Y Tri_X Tri_Z``, the ray's luminous flux and its source's colour at that luminance."""
    counts = _allocate(fluxes, n_rays)
    for i, (s, flux, k) in enumerate(zip(model.sources, fluxes, counts, strict=True)):
        if k == 0:
            continue
        table = _DirectionTable(s)
        for start in range(0, int(k), block):
            m = min(block, int(k) - start)
            rays = np.empty((m, 7 if colour is None else 10), dtype=np.float64)
            r = s.radius_m * np.sqrt(rng.random(m))
            a = rng.random(m) * 2.0 * math.pi
            rays[:, 0] = 1000.0 * (s.centre_m[0] + r * np.cos(a))
            rays[:, 1] = 1000.0 * (s.centre_m[1] + r * np.sin(a))
            rays[:, 2] = 0.0
            rays[:, 3:6] = table.draw(m, rng)
            rays[:, 6] = flux / k
            if colour is not None:
                rays[:, 7] = flux / k * colour.lumens_per_unit[i]
                rays[:, 8] = rays[:, 7] * colour.x_over_y[i]
                rays[:, 9] = rays[:, 7] * colour.z_over_y[i]
            yield rays.astype("<f4")


def _rays_flux(fluxes: np.ndarray, n_rays: int, factors: Sequence[float] | None = None) -> float:
    """The sum of the rays' float32 fluxes, known before they are drawn: ``n_s`` rays of
    ``float32(Φ_s / n_s · factor_s)`` each (``factors``: each source's lm per model unit × sr for the
    luminous flux; 1 for the radiant)."""
    counts = _allocate(fluxes, n_rays)
    factors = [1.0] * len(fluxes) if factors is None else factors
    return float(
        sum(int(k) * float(np.float32(f / k * w)) for f, k, w in zip(fluxes, counts, factors, strict=True) if k > 0)
    )


@dataclass(frozen=True)
class RayColour:
    """What the tristimulus columns carry: every ray its source's colour (CIE 1931 XYZ of the
    source's chromaticity) at the ray's luminous flux ``Tri_Y = phi · lumens_per_unit[s]``.

    ``lumens_per_unit[s]`` is the files' one scale (the calibration, the lamp flux over the
    light's flux, or 1 for relative) times the source's luminance per unit of intensity over the
    light's (``relative_luminance`` of its colour, flux-weighed mean 1): the luminous flux adds
    up to the far-field files' and is shared among the sources by their luminance.
    ``absolute``: whether ``Tri_Y`` is lumens (a calibration or a lamp flux was given)."""

    x_over_y: tuple[float, ...]
    z_over_y: tuple[float, ...]
    lumens_per_unit: tuple[float, ...]
    absolute: bool


def ray_colour(model: LightModel, fluxes: np.ndarray, factor: float, absolute: bool) -> RayColour | None:
    """The tristimulus columns' colours and scales, or None where a source has no XYZ (the run had no
    colour matrices, or the channels were not measured apart): then the file has no colour columns."""
    rows = []
    for s in model.sources:
        v = s.chromaticity.get("XYZ")
        if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(c, (int, float)) for c in v)):
            return None
        if not (all(math.isfinite(c) for c in v) and v[1] > 0):
            return None
        rows.append((float(v[0]) / float(v[1]), float(v[2]) / float(v[1])))
    luminance = np.array([s.chromaticity.get("relative_luminance", math.nan) for s in model.sources], dtype=float)
    if not np.all(np.isfinite(luminance) & (luminance > 0)):
        luminance = np.ones(len(rows))  # a model without it: by the camera signal
    luminance /= float(np.sum(fluxes * luminance) / np.sum(fluxes))
    return RayColour(
        tuple(r[0] for r in rows), tuple(r[1] for r in rows), tuple(float(factor * w) for w in luminance), absolute
    )


def _tm25_texts(
    model: LightModel, name: str | None, manufacturer: str, seed: int, colour: RayColour | None
) -> dict[str, str]:
    """The nine text fields (4.7.3) by name: the light, who made the model and the file, and how."""
    prov = model.provenance
    run = str(prov.get("run_id") or "unknown run")
    unit_note = "W (radiant flux)" if model.units == "W/sr" else "relative units (uncalibrated measurement)"
    absolute = absolute_note(model)
    if absolute is not None:
        unit_note += f"; luminous flux in lm: {absolute}"
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
            f"frame (emission towards +z)." + _colour_note(model, colour)
        ),
        "data_reference": f"run {run}, file {prov.get('run_file') or 'unknown'}",
    }


def _colour_note(model: LightModel, colour: RayColour | None) -> str:
    """The light's and each source's colour, for the additional information (4.7.3.8), and what the
    tristimulus columns hold: TM-25-13's header has no colour field, and its spectral tables need a
    spectrum, which a three-channel camera does not measure."""
    if not model.chromaticity:
        return ""
    sources = "; ".join(f"{s.name}: {describe(s.chromaticity)}" for s in model.sources if s.chromaticity)
    note = f" Colour of the whole light: {describe(model.chromaticity)}. Per source: {sources}."
    if colour is not None:
        units = "lm"
        if not colour.absolute:
            units = "relative units (phi times the source's relative luminance; no lumens given)"
        note += (
            f" Columns Tri_Y, Tri_X, Tri_Z: each ray's CIE 1931 2 deg tristimulus values, its source's "
            f"chromaticity at the ray's luminous flux Tri_Y in {units}."
        )
    return note


def _tm25_header_and_flags(
    creation_method: int, radiant_flux: float, luminous_flux: float, n_rays: int, colour: bool
) -> bytes:
    """The header (4.7.1) with the current date and time and no spectrum, then the column flags (4.7.2):
    position, direction and radiant flux, and with ``colour`` the luminous flux and the tristimulus
    columns (TM-25-13 allows them with spectrum type 0 only, and the tristimulus flag only with the
    luminous flux's)."""
    now = _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().encode("ascii")[:28]
    nan = float("nan")
    # File type, version, creation method, luminous and radiant flux, rays, date and time, start position,
    # spectrum type, wavelength and its range, spectral tables, additional columns, additional text (bytes).
    header = _HEADER.pack(
        b"TM25", 2013, creation_method, luminous_flux, radiant_flux, n_rays, now, 0, 0, nan, nan, nan, 0, 0, 0
    )
    c = int(colour)
    return header + struct.pack("<8i", 1, 1, 1, 0, c, 0, c, 0)


def write_tm25(
    model: LightModel,
    path: str | os.PathLike[str],
    n_rays: int,
    *,
    seed: int,
    name: str | None = None,
    manufacturer: str = "unknown",
    creation_method: int = 1,
    calibration: float | None = None,
    lamp_lumens: float | None = None,
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
    calibration, lamp_lumens : float, optional
        As in :func:`~processing.exports.write_ies`: candela per model unit, or the lamp flux
        the rays' luminous flux adds up to. They scale the luminous flux column ``Tri_Y`` (lm);
        without either it is relative (the ray's ``phi``) and the header's luminous flux NaN.

    Returns
    -------
    Path
        The file written.

    Notes
    -----
    Positions are millimetres in the light frame (the plane at z = 0, emission towards +z);
    the flux column is radiant flux (``phi``, flag 4.7.2.3) in the model's units × sr: W
    when the model is W/sr, relative otherwise (text field 4.7.3.8 says which). The header's
    luminous flux is NaN (not given) unless ``calibration`` or ``lamp_lumens`` is, the spectrum
    type 0 (none).

    Where every source has a colour in CIE XYZ (``chromaticity["XYZ"]``), the rays also carry
    the luminous flux and tristimulus columns (flags 4.7.2.5 and 4.7.2.7): ``Tri_Y`` the ray's
    luminous flux (``phi`` times the calibration, or relative), ``Tri_X``, ``Tri_Z`` its source's
    ``X/Y``, ``Z/Y`` times ``Tri_Y``. The sum of the rays' tristimulus values is the whole
    light's colour, each source weighed by its flux, in any direction or region of the rays.

    The rays are drawn and written :data:`RAY_BLOCK` at a time, so the memory in use does
    not grow with ``n_rays`` (about 20 MB for any count); the header's flux, the sum of the
    rays' float32 fluxes, is known before they are drawn. The same seed writes the same file.
    """
    path = Path(path)
    if isinstance(n_rays, bool) or not isinstance(n_rays, (int, np.integer)) or n_rays < 1:
        raise ExportError(f"{path}: n_rays: must be a positive integer, got {n_rays!r}")
    if creation_method not in (0, 1):
        raise ExportError(
            f"{path}: creation_method: must be 0 (simulation) or 1 (measurement), got {creation_method!r}"
        )
    fluxes = _emitting_fluxes(path, model, n_rays)
    factor, _, absolute = far_field_scaling(path, float(fluxes.sum()), np.ones(1), calibration, lamp_lumens)
    if calibration is None and lamp_lumens is None:
        factor = 1.0  # relative: the luminous flux column is the ray's flux in the model's units
    colour = ray_colour(model, fluxes, factor, absolute or lamp_lumens is not None)
    total = _rays_flux(fluxes, int(n_rays))
    luminous = math.nan
    if colour is not None and colour.absolute:
        luminous = _rays_flux(fluxes, int(n_rays), colour.lumens_per_unit)
    texts = _tm25_texts(model, name, manufacturer, seed, colour)
    head = _tm25_header_and_flags(int(creation_method), total, luminous, int(n_rays), colour is not None)
    text = b"".join(_utf32(texts[k], _TEXT_BYTES) for k in _TEXT_FIELDS)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(head + text)  # no spectral tables, column labels or additional text
            for block in _ray_blocks(model, fluxes, int(n_rays), np.random.default_rng(seed), colour):
                f.write(block.data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
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

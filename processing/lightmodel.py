"""The light model: the measured light as point sources on its plane, and its file.

A :class:`LightModel` is what a run's processing ends with (``docs/measurement.md``,
"The light-source model"): sources ``s`` at ``p_s = (u_s, v_s, 0)`` on the light plane, each with a
continuous radiant intensity ``I_s(θ, φ)`` fitted to its samples (:mod:`processing.fit`).
It answers the questions the rest of the project asks of a light — the intensity of one
source, the far field of the whole light, the irradiance on a surface close by — and it is
saved as a small, versioned, human-readable JSON file (``docs/light-model.md``).

All positions are metres and all angles radians, in the **light frame**: the plane is
``z = 0``, the light emits towards ``+z``; θ is the zenith from ``+z`` and φ the azimuth from
``+x``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import roots_legendre

from drivers.config_files import read_json
from processing.fit import FitError, IntensityFit, Samples

__all__ = [
    "LIGHT_MODEL_FORMAT",
    "LIGHT_MODEL_VERSION",
    "LightModel",
    "LightModelError",
    "SourceModel",
    "describe_fitted",
    "samples_table",
]

LIGHT_MODEL_FORMAT = "mirrorgonio-light-model"
LIGHT_MODEL_VERSION = 1
UNITS = ("W/sr", "relative")
_SAMPLE_COLUMNS = ("theta", "phi", "intensity", "sigma", "position")
_HALF_PI = 0.5 * math.pi


class LightModelError(ValueError):
    """An invalid light model, or an unreadable or foreign light-model file (one line naming it)."""


def describe_fitted(record: dict[str, Any], digits: str) -> str:
    """One of the camera's numbers fitted to the data, in words, from its record (the light
    model's provenance ``aperture_m`` or ``sensor_distance_m``; ``digits`` formats it in mm):
    "0.2004 mm fitted to the data (the rig says 0.2 mm; χ²/pixel 1.063 against 1.07)".

    Examples
    --------
    >>> record = {"fitted_m": 2.004e-4, "described_m": 2e-4, "chi2_per_pixel": 1.063, "chi2_per_pixel_described": 1.07}
    >>> describe_fitted(record, ".4g")
    '0.2004 mm fitted to the data (the rig says 0.2 mm; χ²/pixel 1.063 against 1.07)'
    """
    return (
        f"{1e3 * record['fitted_m']:{digits}} mm fitted to the data (the rig says "
        f"{1e3 * record['described_m']:{digits}} "
        f"mm; χ²/pixel {record['chi2_per_pixel']:.4g} against {record['chi2_per_pixel_described']:.4g})"
    )


def samples_table(
    samples: Samples, positions: ArrayLike | None = None, cell_sum_intensity: ArrayLike | None = None
) -> dict[str, list[float] | list[int]]:
    """The samples of one source as the light model stores them: a table of plain lists.

    Parameters
    ----------
    samples : Samples
        The samples the source's fit was made from.
    positions : array_like of int, optional
        Schedule position of each sample (default ``0 .. n−1``).
    cell_sum_intensity : array_like, optional
        The fast-path flux-sum estimate at the same positions, for comparison.

    Returns
    -------
    dict
        ``theta``, ``phi``, ``intensity``, ``sigma``, ``position`` (and
        ``cell_sum_intensity`` when given), each a list of one value per sample.
    """
    n = len(samples)
    positions = np.arange(n) if positions is None else np.asarray(positions)
    table: dict[str, list[float] | list[int]] = {
        "theta": [float(v) for v in samples.theta],
        "phi": [float(v) for v in samples.phi],
        "intensity": [float(v) for v in samples.intensity],
        "sigma": [float(v) for v in samples.sigma],
        "position": [int(v) for v in positions],
    }
    if cell_sum_intensity is not None:
        table["cell_sum_intensity"] = [float(v) for v in np.asarray(cell_sum_intensity, dtype=float)]
    lengths = {k: len(v) for k, v in table.items()}
    if len(set(lengths.values())) != 1:
        raise LightModelError(
            f"samples: columns differ in length ({', '.join(f'{k} {v}' for k, v in lengths.items())})"
        )
    return table


@dataclass
class SourceModel:
    """One point source of the light.

    Attributes
    ----------
    name : str
        Its name, unique in the model.
    centre_m : tuple of float
        ``(u, v)``, its position on the light plane, metres.
    radius_m : float
        Radius of its emitting disc, metres (0 for a true point).
    fit : IntensityFit
        Its radiant intensity ``I_s(θ, φ)``.
    samples : dict
        The samples the fit was made from (:func:`samples_table`): lists ``theta``,
        ``phi``, ``intensity``, ``sigma``, ``position`` and optionally ``cell_sum_intensity``.
    colour : tuple of float
        ``(R, G, B)``: the source's intensity in each camera channel relative to ``I_s``
        (which is the channel mean), scaled to a mean of 1; ``(1, 1, 1)`` for a grey
        source. Measured through the camera's own channels, as the object is: so the
        reflectance step's albedo does not take on the light's tint.
    chromaticity : dict
        The source's colour as a person sees it (:mod:`processing.colour`): ``basis`` (what
        the numbers are), ``camera_rgb``, and where the run's camera has colour matrices
        ``XYZ``, ``x``, ``y``, ``u_prime``, ``v_prime``, ``cct_k``, ``duv``, and
        ``over_theta`` (the same in bins of θ); empty where not measured (cell sums, a model
        from before colour was kept).
    centre_sigma_m : tuple of float or None
        The 1σ of ``centre_m`` where the centre was found in the data (the larger of the
        least-squares and the position-clustered estimate); None for a layout that was given.
    """

    name: str
    centre_m: tuple[float, float]
    radius_m: float
    fit: IntensityFit
    samples: dict[str, Any] = field(default_factory=dict)
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    chromaticity: dict[str, Any] = field(default_factory=dict)
    centre_sigma_m: tuple[float, float] | None = None

    def __post_init__(self):
        self.name = str(self.name)
        u, v = self.centre_m = self._pair("centre_m", self.centre_m)
        self.radius_m = float(self.radius_m)
        if not (math.isfinite(u) and math.isfinite(v)):
            raise LightModelError(f"source {self.name!r}: centre_m must be finite, got {self.centre_m}")
        if not (self.radius_m >= 0 and math.isfinite(self.radius_m)):
            raise LightModelError(f"source {self.name!r}: radius_m must be finite and >= 0, got {self.radius_m}")
        if not isinstance(self.fit, IntensityFit):
            raise LightModelError(f"source {self.name!r}: fit must be an IntensityFit, got {type(self.fit).__name__}")
        if not isinstance(self.samples, dict):
            raise LightModelError(f"source {self.name!r}: samples must be a table (dict of lists)")
        try:
            colour = np.asarray(self.colour, dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise LightModelError(
                f"source {self.name!r}: colour must be three numbers (R, G, B), got {self.colour!r}"
            ) from None
        if not (np.all(np.isfinite(colour)) and np.all(colour > 0)):
            raise LightModelError(f"source {self.name!r}: colour must be three finite numbers > 0, got {self.colour!r}")
        mean = colour.mean()
        # Scaled to a mean of 1, unless it is so already (to rounding): a saved model reads back bit for bit.
        self.colour = tuple(float(c) for c in (colour if abs(mean - 1.0) < 1e-12 else colour / mean))
        if not isinstance(self.chromaticity, dict):
            raise LightModelError(f"source {self.name!r}: chromaticity must be a table (dict)")
        if self.centre_sigma_m is not None:
            su, sv = self.centre_sigma_m = self._pair("centre_sigma_m", self.centre_sigma_m)
            if not (su >= 0 and sv >= 0 and math.isfinite(su) and math.isfinite(sv)):
                raise LightModelError(f"source {self.name!r}: centre_sigma_m must be finite and >= 0")

    def _pair(self, field: str, value: object) -> tuple[float, float]:
        """``value`` as two floats (u, v), or the one-line error naming the source and the field."""
        try:
            u, v = (float(c) for c in value)  # type: ignore[attr-defined]
        except (TypeError, ValueError):
            raise LightModelError(f"source {self.name!r}: {field} must be two numbers (u, v), got {value!r}") from None
        return u, v

    def intensity(self, theta: ArrayLike, phi: ArrayLike = 0.0) -> np.ndarray:
        """``I_s(θ, φ)``: the fit, clipped at zero, and zero behind the plane (θ > 90°)."""
        theta, phi = np.broadcast_arrays(np.asarray(theta, dtype=float), np.asarray(phi, dtype=float))
        values = self.fit(theta, phi)
        return np.where(theta <= _HALF_PI, np.maximum(values, 0.0), 0.0)

    def flux(self, n_theta: int = 400, n_phi: int = 180) -> float:
        """``∫ I_s dΩ`` over the hemisphere: Gauss–Legendre in θ, the periodic trapezoid rule in φ."""
        theta, w_theta = _hemisphere_nodes(n_theta)
        if self.fit.method == "gaussian-2d":
            phi = np.arange(n_phi) * (2.0 * math.pi / n_phi)
            values = self.intensity(theta[:, None], phi[None, :])
            return float(np.sum(values.mean(axis=1) * w_theta) * 2.0 * math.pi)
        return float(np.sum(self.intensity(theta) * w_theta) * 2.0 * math.pi)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able record of the source."""
        return {
            "name": self.name,
            "centre_m": list(self.centre_m),
            **({"centre_sigma_m": list(self.centre_sigma_m)} if self.centre_sigma_m is not None else {}),
            "radius_m": self.radius_m,
            "colour": list(self.colour),
            **({"chromaticity": json_ready(self.chromaticity)} if self.chromaticity else {}),
            "fit": self.fit.to_dict(),
            "band": self.band_table(),
            "samples": json_ready(self.samples),
        }

    def band_table(self, step_deg: float = 1.0) -> dict[str, Any]:
        """The fit and its 1σ (:meth:`processing.fit.IntensityFit.band`) over the measured θ, for
        readers without this code: ``theta_deg`` every ``step_deg`` from the range's start to
        its end, ``phi_deg`` (0 alone for a fit symmetric about the axis, every 15° for a 2-D
        one), ``intensity`` and ``sigma`` as ``[phi][theta]``; derived, not read back."""
        lo, hi = (math.degrees(v) for v in self.fit.theta_range)
        theta = np.unique(np.append(np.arange(lo, hi, step_deg), hi)) if hi > lo else np.array([lo])
        phi = np.arange(0.0, 360.0, 15.0) if self.fit.method == "gaussian-2d" else np.zeros(1)
        t, p = np.meshgrid(np.radians(theta), np.radians(phi))
        return {
            "theta_deg": [round(float(v), 4) for v in theta],
            "phi_deg": [float(v) for v in phi],
            "intensity": json_ready(self.intensity(t, p)),
            "sigma": json_ready(self.fit.band(t, p)),
            "model_error": float(self.fit.info.get("model_error", 0.0)),
        }


@lru_cache(maxsize=8)
def _hemisphere_nodes(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes θ on [0, π/2] and their weights times sin θ."""
    x, w = roots_legendre(n)
    theta = 0.25 * math.pi * (x + 1.0)
    return theta, 0.25 * math.pi * w * np.sin(theta)


def json_ready(obj: Any) -> Any:
    """numpy scalars and arrays to plain Python for JSON; non-finite floats become None (null)."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None  # JSON has no NaN: null where no value
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


@dataclass
class LightModel:
    """The measured light: point sources with their own radiant intensity distributions.

    Attributes
    ----------
    sources : list of SourceModel
        The sources, in the order of the run's source layout.
    units : str
        ``"W/sr"`` when the run was radiometrically calibrated, else ``"relative"``.
    provenance : dict
        Where the model comes from: ``run_id``, ``run_file``, ``rig``, ``software_version``,
        ``method`` (e.g. ``"template-unmixing"`` or ``"cell-sums"``),
        ``spatial_resolution_m`` (the point spread's footprint on the light plane), and
        anything else worth keeping (JSON-able).
    quality : dict
        Whether the model can be trusted (:mod:`processing.light_run.quality`): ``status``
        ``ok`` or ``suspect``, the ``reason`` where suspect, and the figures it was judged on;
        empty for a model made without that judgement.
    photometry : dict
        The photometric summary of the whole light (:mod:`processing.photometry`,
        :meth:`~processing.photometry.Photometry.record`) as the processing wrote it with the
        light files; empty for a model made without one. Kept as read, never recomputed.
    chromaticity : dict
        The whole light's colour (:attr:`SourceModel.chromaticity`, the sources weighed by
        their flux); empty where the sources have none.

    Notes
    -----
    The model of the light (``docs/measurement.md``): ``D(r) = Σ_s I_s(θ_s, φ_s)/|r − p_s|²``
    and ``E(r, n) = Σ_s I_s(θ_s, φ_s)·max(0, n·ω_s)/|r − p_s|²``.
    """

    sources: list[SourceModel]
    units: str = "relative"
    provenance: dict[str, Any] = field(default_factory=dict)
    quality: dict[str, Any] = field(default_factory=dict)
    photometry: dict[str, Any] = field(default_factory=dict)
    chromaticity: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.sources = list(self.sources)
        if self.units not in UNITS:
            raise LightModelError(f"units: {self.units!r} is not one of {', '.join(UNITS)}")
        if not self.sources:
            raise LightModelError("sources: a light model needs at least one source")
        for i, s in enumerate(self.sources):
            if not isinstance(s, SourceModel):
                raise LightModelError(f"sources[{i}]: expected a SourceModel, got {type(s).__name__}")
        names = [s.name for s in self.sources]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise LightModelError(f"sources: duplicate name {', '.join(map(repr, dupes))}")
        if not isinstance(self.provenance, dict):
            raise LightModelError("provenance: expected a table (dict)")
        if not isinstance(self.quality, dict):
            raise LightModelError("quality: expected a table (dict)")
        if not isinstance(self.photometry, dict):
            raise LightModelError("photometry: expected a table (dict)")
        if not isinstance(self.chromaticity, dict):
            raise LightModelError("chromaticity: expected a table (dict)")

    # ----------------------------------------------------------------- lookups

    def source(self, source: int | str) -> SourceModel:
        """A source by index or by name (:class:`LightModelError` if there is none)."""
        if isinstance(source, (int, np.integer)) and not isinstance(source, bool):
            if not -len(self.sources) <= source < len(self.sources):
                raise LightModelError(f"source {int(source)}: out of range (the model has {len(self.sources)})")
            return self.sources[int(source)]
        for s in self.sources:
            if s.name == source:
                return s
        raise LightModelError(f"source {source!r}: no such source (known: {', '.join(s.name for s in self.sources)})")

    def intensity(self, source: int | str, theta: ArrayLike, phi: ArrayLike = 0.0) -> np.ndarray:
        """Radiant intensity ``I_s(θ, φ)`` of one source.

        Parameters
        ----------
        source : int or str
            Index or name.
        theta, phi : array_like
            Directions in the light frame, radians.

        Returns
        -------
        ndarray
            The source's fit, clipped at zero (a polynomial may dip below it when
            extrapolated), and zero behind the light plane (θ > 90°).
        """
        return self.source(source).intensity(theta, phi)

    def far_field(self, theta: ArrayLike, phi: ArrayLike = 0.0) -> np.ndarray:
        """``Σ_s I_s(θ, φ)``: the whole light seen from far away, where every source is at one point."""
        theta, phi = np.broadcast_arrays(np.asarray(theta, dtype=float), np.asarray(phi, dtype=float))
        total = np.zeros(theta.shape)
        for s in self.sources:
            total += s.intensity(theta, phi)
        return total

    def on_axis_shares(self) -> tuple[np.ndarray, float]:
        """Each source's share of the on-axis intensity ``I_s(0) / Σ I_s(0)`` (equal shares
        if every ``I_s(0)`` is 0), and ``Σ_s I_s(0)``: how the simplified lights of the
        reflectance step, one point of one colour, weigh the sources."""
        weights = np.array([float(s.intensity(0.0, 0.0)) for s in self.sources])
        total = float(weights.sum())
        shares = weights / total if total > 0 else np.full(len(weights), 1.0 / len(weights))
        return shares, total

    def colour(self) -> np.ndarray:
        """``(R, G, B)`` of the whole light, mean 1: the sources' colours weighted by their
        :meth:`on_axis_shares`."""
        shares, _ = self.on_axis_shares()
        mixed = (shares[:, None] * np.array([s.colour for s in self.sources])).sum(axis=0)
        return mixed / mixed.mean()

    def irradiance_rgb(self, points: ArrayLike, normals: ArrayLike) -> np.ndarray:
        """:meth:`irradiance` per camera channel, (N, 3): each source's term times its
        :attr:`SourceModel.colour`. Its channel mean is :meth:`irradiance`."""
        return self._irradiance(points, normals, rgb=True)

    def irradiance(self, points: ArrayLike, normals: ArrayLike) -> np.ndarray:
        """Irradiance on surfaces close to the light, each source an inverse-square point.

        ``E(r, n) = Σ_s I_s(θ_s, φ_s)·max(0, n·ω_s)/|r − p_s|²`` (``docs/measurement.md``), with
        ``p_s = (u_s, v_s, 0)``, ``(θ_s, φ_s)`` the direction from ``p_s`` to ``r`` and
        ``ω_s`` the unit vector from ``r`` to ``p_s``.

        Parameters
        ----------
        points : array_like (N, 3)
            Surface points ``r`` in the light frame, metres.
        normals : array_like (N, 3) or (3,)
            Their surface normals in the light frame (normalised here).

        Returns
        -------
        ndarray (N,)
            Irradiance in the model's units per m² (W/m² when ``units`` is ``"W/sr"``);
            zero for points on or behind the light plane (``z <= 0``).
        """
        return self._irradiance(points, normals, rgb=False)

    def _irradiance(self, points: ArrayLike, normals: ArrayLike, *, rgb: bool) -> np.ndarray:
        r = np.asarray(points, dtype=float)
        if r.ndim != 2 or r.shape[1] != 3:
            raise LightModelError(f"irradiance: points must be (N, 3), got shape {r.shape}")
        n = np.broadcast_to(np.asarray(normals, dtype=float), r.shape)
        norm = np.linalg.norm(n, axis=1)
        if np.any(~(norm > 0)):
            raise LightModelError("irradiance: normals must be non-zero and finite")
        n = n / norm[:, None]
        front = r[:, 2] > 0
        E = np.zeros((len(r), 3) if rgb else len(r))
        rf, nf = r[front], n[front]
        for s in self.sources:
            d = rf - np.array([s.centre_m[0], s.centre_m[1], 0.0])
            dist2 = np.einsum("ij,ij->i", d, d)
            dist = np.sqrt(dist2)
            theta = np.arccos(np.clip(d[:, 2] / dist, -1.0, 1.0))
            phi = np.arctan2(d[:, 1], d[:, 0])
            cos_in = np.maximum(0.0, -np.einsum("ij,ij->i", nf, d) / dist)  # n·ω_s, ω_s = −d/|d|
            term = s.intensity(theta, phi) * cos_in / dist2
            E[front] += term[:, None] * np.asarray(s.colour) if rgb else term
        return E

    def total_flux(self) -> float:
        """``∫ Σ_s I_s dΩ`` over the hemisphere in front of the plane (numerical), in the model's units × sr."""
        return float(sum(s.flux() for s in self.sources))

    # ----------------------------------------------------------------- the file

    def to_dict(self) -> dict[str, Any]:
        """The JSON-able record written by :meth:`save`."""
        return {
            "format": LIGHT_MODEL_FORMAT,
            "format_version": LIGHT_MODEL_VERSION,
            "units": self.units,
            "provenance": json_ready(self.provenance),
            **({"quality": json_ready(self.quality)} if self.quality else {}),
            **({"photometry": json_ready(self.photometry)} if self.photometry else {}),
            **({"chromaticity": json_ready(self.chromaticity)} if self.chromaticity else {}),
            "sources": [s.to_dict() for s in self.sources],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, origin: str = "light model") -> LightModel:
        """Rebuild a model from :meth:`to_dict`'s record, checking format and version.

        Raises
        ------
        LightModelError
            One line naming ``origin`` and the offending field.
        """
        if not isinstance(d, dict):
            raise LightModelError(f"{origin}: not a mirrorgonio light model (a JSON {type(d).__name__}, not an object)")
        fmt = d.get("format")
        if fmt != LIGHT_MODEL_FORMAT:
            raise LightModelError(
                f"{origin}: not a mirrorgonio light model (format {fmt!r}, expected {LIGHT_MODEL_FORMAT!r})"
            )
        version = d.get("format_version")
        if isinstance(version, bool) or not isinstance(version, int) or version < 1:
            raise LightModelError(f"{origin}: format_version: {version!r} is not a version number")
        if version > LIGHT_MODEL_VERSION:
            raise LightModelError(
                f"{origin}: format_version {version} is newer than this software reads "
                f"(up to {LIGHT_MODEL_VERSION}): update mirrorgonio"
            )
        for key in ("units", "sources"):
            if key not in d:
                raise LightModelError(f"{origin}: {key}: missing")
        if not isinstance(d["sources"], list):
            raise LightModelError(f"{origin}: sources: expected a list")
        sources = []
        for i, s in enumerate(d["sources"]):
            where = f"{origin}: sources[{i}]"
            if not isinstance(s, dict):
                raise LightModelError(f"{where}: expected an object")
            for key in ("name", "centre_m", "radius_m", "fit"):
                if key not in s:
                    raise LightModelError(f"{where}.{key}: missing")
            try:
                fit = IntensityFit.from_dict(s["fit"])
            except FitError as e:
                raise LightModelError(f"{where}.fit: {str(e).removeprefix('fit record: ')}") from None
            try:
                sources.append(
                    SourceModel(
                        s["name"],
                        tuple(s["centre_m"]),
                        s["radius_m"],
                        fit,
                        s.get("samples", {}),
                        s.get("colour", (1.0, 1.0, 1.0)),
                        s.get("chromaticity", {}),
                        s.get("centre_sigma_m"),
                    )
                )  # files without colours: grey
            except (LightModelError, TypeError, ValueError) as e:
                raise LightModelError(f"{where}: {e}") from None
        try:
            return cls(
                sources,
                d["units"],
                d.get("provenance", {}),
                d.get("quality", {}),
                d.get("photometry", {}),
                d.get("chromaticity", {}),
            )
        except LightModelError as e:
            raise LightModelError(f"{origin}: {e}") from None

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the model as JSON (``docs/light-model.md``), atomically; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            text = _dumps(self.to_dict()) + "\n"
        except (TypeError, ValueError) as e:  # a provenance or table value JSON cannot hold
            raise LightModelError(f"{path}: cannot write ({e})") from None
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> LightModel:
        """Read a light-model file, checking its format and version.

        Raises
        ------
        LightModelError
            One line naming the file: unreadable, not JSON, a foreign JSON, a newer format
            version, or a bad field.
        """
        path = Path(path)
        return cls.from_dict(read_json(path, "light-model file", LightModelError), origin=str(path))


def _dumps(obj: Any, indent: int = 0) -> str:
    """JSON with objects one key a line and lists of numbers on one line: small and readable."""
    pad, inner = " " * indent, " " * (indent + 2)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {_dumps(v, indent + 2)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list):
        if all(not isinstance(v, (dict, list)) for v in obj):
            return json.dumps(obj, allow_nan=False)
        items = [f"{inner}{_dumps(v, indent + 2)}" for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(obj, allow_nan=False)

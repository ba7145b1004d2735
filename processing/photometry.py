"""The photometric summary of the whole light, as a lighting engineer reads a luminaire.

Computed from a :class:`~processing.lightmodel.LightModel` (``docs/light-model.md``,
"Photometry"): the total flux and the flux by 10° zone of γ; the share of it that lies beyond
the θ the sweep measured (where the light files hold the fits' extrapolation); the peak
intensity and its direction; the beam (50 % of peak) and field (10 %) angles in the
C0–C180 and C90–C270 planes; and the near field: the illuminance on a plane at a chosen
distance (30 cm: where the objects are lit) from the model's array of point sources, next to
what one point source of the same far field at the light's centre gives (the far-field
approximation a lighting program makes with an IES file).

Angles follow the far-field files (:mod:`processing.exports`): γ = θ from the light's axis
(photometric nadir), ``C = (360° − φ) mod 360°``. Every figure is in the model's units: the
intensities in ``W/sr`` or ``relative``, the flux in those × sr, the illuminance in those per m².

The **measured range** of a source is ``θ ≤ θmax,s``, the largest θ its samples reach
(``fit.theta_range[1]``): the sweep passes the light's axis, so the θ below the smallest
sampled one lie between samples on either side. With ``extrapolation="none"`` every source
is zero beyond its measured range, as the light files written that way are; with
``"fitted"`` (the default) the fits carry on.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache, partial
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import roots_legendre

from processing.lightmodel import LightModel, SourceModel, json_ready
from processing.options import Extrapolation

__all__ = [
    "NEAR_FIELD_DISTANCE_M",
    "PLANES",
    "NearField",
    "PlaneAngles",
    "Photometry",
    "far_field",
    "ROOM_INDICES",
    "direct_ratios",
    "measured_theta_max",
    "summarize",
]

#: Where the objects are lit: the distance of the near-field plane, metres.
NEAR_FIELD_DISTANCE_M = 0.3
#: The zones of γ the flux is given by (degrees): the 10° zones of a zonal lumen summary.
ZONE_EDGES_DEG = tuple(range(0, 91, 10))
#: The C-planes whose beam and field angles are given, each a pair (the plane's two halves).
PLANES = (("C0", "C180"), ("C90", "C270"))
_THRESHOLDS = {"beam": 0.5, "field": 0.1}
_NODES = 32  # Gauss–Legendre nodes per θ segment: exact to rounding for the fits' smooth lobes
_N_PHI_2D = 72  # the periodic trapezoid rule in φ for the 2-D fits
_STEP_DEG = 0.05  # the γ step the beam and field angles are found on (then interpolated)
#: The room indices ``k`` of EULUMDAT's direct ratios (line 24), in its order.
ROOM_INDICES = (0.6, 0.8, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0)
_ROOM_NODES = 64  # Gauss–Legendre nodes per half axis of the direct ratios' offset plane


def measured_theta_max(source: SourceModel) -> float:
    """The largest θ the source's samples reach, radians: its measured range is ``θ ≤`` it."""
    return float(source.fit.theta_range[1])


def _source_intensity(source: SourceModel, theta: np.ndarray, phi: np.ndarray, measured_only: bool) -> np.ndarray:
    values = source.intensity(theta, phi)
    return np.where(theta <= measured_theta_max(source), values, 0.0) if measured_only else values


def far_field(
    model: LightModel, theta: ArrayLike, phi: ArrayLike = 0.0, extrapolation: str = Extrapolation.FITTED
) -> np.ndarray:
    """``Σ_s I_s(θ, φ)`` as the light files hold it: with the fits' extrapolation beyond each
    source's measured θ (``"fitted"``), or zero there (``"none"``).

    Parameters
    ----------
    model : LightModel
    theta, phi : array_like
        Directions in the light frame, radians; broadcast against each other.
    extrapolation : {"fitted", "none"}

    Returns
    -------
    ndarray
        The far field in the model's units.
    """
    measured_only = Extrapolation(extrapolation) is Extrapolation.NONE
    theta, phi = np.broadcast_arrays(np.asarray(theta, dtype=float), np.asarray(phi, dtype=float))
    total = np.zeros(theta.shape)
    for s in model.sources:
        total += _source_intensity(s, theta, phi, measured_only)
    return total


@lru_cache(maxsize=4)
def _unit_nodes(n: int) -> tuple[np.ndarray, np.ndarray]:
    return roots_legendre(n)


def _segment_flux(source: SourceModel, lo: float, hi: float) -> float:
    """``∫ I_s dΩ`` over ``lo ≤ θ ≤ hi`` (radians): Gauss–Legendre in θ, the trapezoid rule in φ."""
    if hi <= lo:
        return 0.0
    x, w = _unit_nodes(_NODES)
    theta = 0.5 * (hi - lo) * (x + 1.0) + lo
    weights = 0.5 * (hi - lo) * w * np.sin(theta)
    if source.fit.method == "gaussian-2d":  # the only fit that depends on φ
        phi = np.arange(_N_PHI_2D) * (2.0 * math.pi / _N_PHI_2D)
        values = source.intensity(theta[:, None], phi[None, :]).mean(axis=1)
    else:
        values = source.intensity(theta)
    return float(np.sum(values * weights) * 2.0 * math.pi)


def _zone_fluxes(model: LightModel, edges_deg: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``(measured, beyond)``: each zone's flux within the sources' measured ranges, and beyond them."""
    edges = np.radians(edges_deg)
    measured, beyond = np.zeros(len(edges) - 1), np.zeros(len(edges) - 1)
    for s in model.sources:
        top = measured_theta_max(s)
        for k, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            measured[k] += _segment_flux(s, a, min(b, top))
            beyond[k] += _segment_flux(s, max(a, top), b)
    return measured, beyond


@dataclass(frozen=True)
class PlaneAngles:
    """The beam or field angle in one C-plane pair: where the intensity falls to ``threshold``
    × the peak on either side of the plane's own maximum.

    Attributes
    ----------
    plane : str
        ``"C0-C180"`` or ``"C90-C270"``.
    threshold : float
        0.5 (beam) or 0.1 (field), of the light's peak intensity.
    half_angles_deg : dict
        The crossing's γ in each half of the plane (``{"C0": …, "C180": …}``), degrees;
        None where the intensity does not fall that low in front of the plane.
    angle_deg : float or None
        The full angle between the two crossings, degrees.
    beyond_measured : bool
        A crossing lies beyond the θ every source was measured to: the angle rests on the
        fits' extrapolation.
    """

    plane: str
    threshold: float
    half_angles_deg: dict[str, float | None]
    angle_deg: float | None
    beyond_measured: bool


def _crossing(gamma: np.ndarray, values: np.ndarray, start: int, level: float) -> float | None:
    """The first γ past index ``start`` (outward along ``gamma``) where ``values`` falls below
    ``level``, interpolated linearly between the grid's points."""
    below = np.flatnonzero(values[start:] < level)
    if not below.size:
        return None
    i = start + int(below[0])
    if i == 0:
        return float(gamma[0])
    v0, v1 = values[i - 1], values[i]
    t = (v0 - level) / (v0 - v1) if v0 != v1 else 0.0
    return float(gamma[i - 1] + t * (gamma[i] - gamma[i - 1]))


def _plane_angles(
    model: LightModel, halves: tuple[str, str], peak: float, extrapolation: str, fully_measured_deg: float
) -> dict[str, PlaneAngles]:
    """Beam and field angles in the plane made of two C half-planes (``("C0", "C180")``)."""
    gamma = np.arange(0.0, 92.0 + _STEP_DEG / 2, _STEP_DEG)  # past 90°: behind the plane, zero
    profiles = []
    for half in halves:
        c = float(half[1:])
        profiles.append(far_field(model, np.radians(gamma), np.radians(-c), extrapolation))
    # The plane's profile on signed γ (the second half negative), searched outward from its maximum.
    signed = np.concatenate([-gamma[::-1], gamma[1:]])
    values = np.concatenate([profiles[1][::-1], profiles[0][1:]])
    top = int(np.argmax(values))
    out = {}
    for kind, threshold in _THRESHOLDS.items():
        level = threshold * peak
        right = _crossing(signed, values, top, level) if values[top] >= level else None
        left = _crossing(signed[::-1], values[::-1], len(signed) - 1 - top, level) if values[top] >= level else None
        half_angles = {halves[0]: right, halves[1]: None if left is None else -left}
        angle = right - left if right is not None and left is not None else None
        reach = [abs(v) for v in (right, left) if v is not None]
        out[kind] = PlaneAngles(
            f"{halves[0]}-{halves[1]}",
            threshold,
            half_angles,
            angle,
            any(r > fully_measured_deg + 1e-9 for r in reach),
        )
    return out


def _peak(model: LightModel, extrapolation: str) -> tuple[float, float, float, bool]:
    """``(intensity, γ°, C°, symmetric)``: the far field's largest value on a 0.1° × 2.5° grid;
    ``symmetric`` when no source's fit depends on φ (the far field is then the same in every C)."""
    symmetric = all(s.fit.method != "gaussian-2d" for s in model.sources)
    gamma = np.arange(0.0, 90.0 + 1e-9, 0.1)
    c = np.zeros(1) if symmetric else np.arange(0.0, 360.0, 2.5)
    table = far_field(model, np.radians(gamma)[None, :], np.radians(-c)[:, None], extrapolation)
    i, j = np.unravel_index(int(np.argmax(table)), table.shape)
    return float(table[i, j]), float(gamma[j]), float(c[i]), symmetric


def direct_ratios(
    model: LightModel, extrapolation: str = Extrapolation.FITTED, room_indices: tuple[float, ...] = ROOM_INDICES
) -> tuple[float, ...]:
    """The direct ratio for each room index: the share of the light's flux that falls directly on
    the work plane of a square room of index ``k``, the luminaires spread evenly over its ceiling.

    The room: side ``a``, the luminaires at height ``h`` above the work plane, ``k = a² / (2ah) =
    a / 2h``, walls and ceiling taking whatever misses the work plane; the light hangs axis down,
    its C0 along one wall. Luminaires spread evenly over the ceiling (the limit of a dense
    regular array) make the share of a light at ``p`` landing on the work plane, averaged over
    ``p``, a single integral over the offset ``d`` from a luminaire to the point lit::

        DR(k) = (1/Φ) ∫∫ (1 − |dx|/a)(1 − |dy|/a) · I(θ, φ) cos³θ / h² d(dx) d(dy)

    over ``|dx|, |dy| < a`` (the two squares' overlap when shifted by ``d``), ``tan θ = |d|/h``,
    ``φ = atan2(dy, dx)``; ``Φ`` the flux in front of the light. Computed by Gauss–Legendre in
    ``atan(dx/h)`` and ``atan(dy/h)``, 64 nodes each side of the nadir.

    Parameters
    ----------
    model : LightModel
    extrapolation : {"fitted", "none"}
        The light the files hold beyond the measured θ (:func:`far_field`).
    room_indices : tuple of float
        The ``k`` (EULUMDAT's ten by default).

    Returns
    -------
    tuple of float
        The direct ratios, fractions of 1.
    """
    x, w = _unit_nodes(_ROOM_NODES)
    flux = float(sum(_segment_flux_of(model, s, extrapolation) for s in model.sources))
    out = []
    for k in room_indices:
        a = 2.0 * float(k)  # h = 1
        top = math.atan(a)
        t = np.concatenate([0.5 * top * (x - 1.0), 0.5 * top * (x + 1.0)])  # atan(d) over (-a, 0) and (0, a)
        d = np.tan(t)
        weight = np.concatenate([0.5 * top * w, 0.5 * top * w]) / np.cos(t) ** 2 * (1.0 - np.abs(d) / a)
        dx, dy = np.meshgrid(d, d, indexing="ij")
        r2 = dx * dx + dy * dy
        cos_t = 1.0 / np.sqrt(1.0 + r2)
        values = far_field(model, np.arccos(cos_t), np.arctan2(dy, dx), extrapolation) * cos_t**3
        out.append(float(weight @ values @ weight) / flux)
    return tuple(out)


def _segment_flux_of(model: LightModel, source: SourceModel, extrapolation: str) -> float:
    """A source's flux in front of the light, up to its measured θ only with ``extrapolation="none"``."""
    top = measured_theta_max(source) if Extrapolation(extrapolation) is Extrapolation.NONE else 0.5 * math.pi
    return _segment_flux(source, 0.0, min(top, 0.5 * math.pi))


@dataclass(frozen=True)
class NearField:
    """The illuminance on a plane facing the light at ``distance_m``, on a square grid.

    Attributes
    ----------
    distance_m : float
        The plane's distance from the light plane (``z``), metres.
    centre_m : tuple of float
        ``(u, v)``: the light's centre, the middle of its luminous opening, where the one
        point source of the far-field approximation sits.
    x_m, y_m : ndarray
        The grid's coordinates on the plane (light frame x and y), metres.
    array : ndarray
        The illuminance from the model's array of point sources, ``(len(y), len(x))``.
    point : ndarray
        The illuminance from one point source of the whole light's far field at ``centre_m``.
    """

    distance_m: float
    centre_m: tuple[float, float]
    x_m: np.ndarray
    y_m: np.ndarray
    array: np.ndarray
    point: np.ndarray

    def difference_percent(self) -> np.ndarray:
        """``(point − array) / max(array)`` in %: the far-field approximation's error, of the peak."""
        return 100.0 * (self.point - self.array) / float(np.max(self.array))

    def largest_differences(self) -> tuple[float, float]:
        """``(of the peak, local)``: the largest ``|point − array|`` in % of the array's peak
        illuminance, and the largest ``|point / array − 1|`` in % where the array gives at
        least 10 % of its peak (the lit field)."""
        peak = float(np.max(self.array))
        lit = self.array >= 0.1 * peak
        local = np.abs(self.point[lit] / self.array[lit] - 1.0)
        return float(np.max(np.abs(self.difference_percent()))), 100.0 * float(np.max(local))


def opening_centre(model: LightModel) -> tuple[float, float]:
    """``(u, v)``: the middle of the light's luminous opening (the box round the sources' discs)."""
    lo = [min(s.centre_m[k] - s.radius_m for s in model.sources) for k in (0, 1)]
    hi = [max(s.centre_m[k] + s.radius_m for s in model.sources) for k in (0, 1)]
    return 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])


def _plane_illuminance(
    model: LightModel, points: np.ndarray, extrapolation: str, centre: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Illuminance on plane points facing the light (normal −z): from each source at its place,
    and from one point at ``centre`` with the whole far field."""
    measured_only = Extrapolation(extrapolation) is Extrapolation.NONE

    def from_point(u: float, v: float, intensity: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
        d = points - np.array([u, v, 0.0])
        r2 = np.einsum("ij,ij->i", d, d)
        cos_t = d[:, 2] / np.sqrt(r2)
        theta, phi = np.arccos(np.clip(cos_t, -1.0, 1.0)), np.arctan2(d[:, 1], d[:, 0])
        return intensity(theta, phi) * cos_t / r2  # the plane's normal along the axis: cos in = cos θ

    array = np.zeros(len(points))
    for s in model.sources:
        array += from_point(*s.centre_m, partial(_source_intensity, s, measured_only=measured_only))
    point = from_point(*centre, lambda t, p: far_field(model, t, p, extrapolation))
    return array, point


def near_field(
    model: LightModel,
    distance_m: float = NEAR_FIELD_DISTANCE_M,
    half_width_m: float | None = None,
    n: int = 121,
    extrapolation: str = Extrapolation.FITTED,
) -> NearField:
    """The illuminance on a plane at ``distance_m`` in front of the light, from its array of
    sources and from the far-field approximation (:class:`NearField`).

    Parameters
    ----------
    model : LightModel
    distance_m : float
        The plane's distance, metres (30 cm by default).
    half_width_m : float, optional
        Half the side of the square shown; default ``distance_m · tan 60°``.
    n : int
        Grid points per side.
    extrapolation : {"fitted", "none"}
    """
    centre = opening_centre(model)
    half = distance_m * math.tan(math.radians(60.0)) if half_width_m is None else half_width_m
    x = centre[0] + np.linspace(-half, half, n)
    y = centre[1] + np.linspace(-half, half, n)
    xx, yy = np.meshgrid(x, y)
    points = np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, distance_m)])
    array, point = _plane_illuminance(model, points, extrapolation, centre)
    return NearField(distance_m, centre, x, y, array.reshape(xx.shape), point.reshape(xx.shape))


@dataclass(frozen=True)
class Photometry:
    """The photometric summary of the whole light (:func:`summarize`).

    Attributes
    ----------
    extrapolation : str
        ``"fitted"`` or ``"none"``: what the figures (and the light files) hold beyond the
        measured θ.
    units : str
        The model's intensity units (``W/sr`` or ``relative``).
    measured_theta_max_deg : dict
        Each source's measured range ``θ ≤`` this, degrees, by name.
    zone_edges_deg : tuple of int
        The zones' γ edges, degrees.
    zone_measured, zone_beyond : ndarray
        Each zone's flux within the sources' measured ranges and beyond them (zero beyond
        with ``extrapolation="none"``).
    fitted_beyond : float
        The flux the fits put beyond the measured ranges, whatever ``extrapolation`` is.
    peak : tuple
        ``(intensity, γ°, C°, symmetric)``.
    angles : dict
        ``{"beam": {plane: PlaneAngles}, "field": {…}}``.
    near : NearField or None
        The illuminance at :data:`NEAR_FIELD_DISTANCE_M`, when asked for.
    direct_ratios : tuple of float
        :func:`direct_ratios` for :data:`ROOM_INDICES`.
    """

    extrapolation: str
    units: str
    measured_theta_max_deg: dict[str, float]
    zone_edges_deg: tuple[int, ...]
    zone_measured: np.ndarray
    zone_beyond: np.ndarray
    fitted_beyond: float
    peak: tuple[float, float, float, bool]
    angles: dict[str, dict[str, PlaneAngles]]
    near: NearField | None
    direct_ratios: tuple[float, ...] = ()

    @property
    def total_flux(self) -> float:
        """The flux in front of the light plane, the model's units × sr."""
        return float(self.zone_measured.sum() + self.zone_beyond.sum())

    @property
    def beyond_fraction(self) -> float:
        """The share of :attr:`total_flux` beyond the sources' measured θ."""
        return float(self.zone_beyond.sum()) / self.total_flux

    @property
    def fitted_beyond_fraction(self) -> float:
        """The share of the fitted light's flux that lies beyond the measured θ."""
        return self.fitted_beyond / (float(self.zone_measured.sum()) + self.fitted_beyond)

    @property
    def light_theta_max_deg(self) -> tuple[float, float]:
        """``(every source, some source)``: the θ up to which every source, and some source, was measured."""
        values = list(self.measured_theta_max_deg.values())
        return min(values), max(values)

    def angle(self, kind: str, plane: str) -> float | None:
        """The ``"beam"`` or ``"field"`` angle in ``"C0-C180"`` or ``"C90-C270"``, degrees."""
        return self.angles[kind][plane].angle_deg

    def record(self) -> dict[str, Any]:
        """The light model JSON's ``photometry`` section (``docs/light-model.md``)."""
        flux_units = {"W/sr": "W"}.get(self.units, "relative")
        total = self.total_flux
        zones = []
        cumulative = 0.0
        for k, (a, b) in enumerate(zip(self.zone_edges_deg[:-1], self.zone_edges_deg[1:], strict=True)):
            flux = float(self.zone_measured[k] + self.zone_beyond[k])
            cumulative += flux
            zones.append(
                {
                    "gamma_deg": [a, b],
                    "flux": flux,
                    "percent": 100.0 * flux / total,
                    "cumulative_percent": 100.0 * cumulative / total,
                    "beyond_measured_percent": 100.0 * float(self.zone_beyond[k]) / flux if flux > 0 else 0.0,
                }
            )
        intensity, gamma, c, symmetric = self.peak
        out: dict[str, Any] = {
            "extrapolation": self.extrapolation,
            "intensity_units": self.units,
            "flux_units": flux_units,
            "measured_theta_max_deg": min(self.measured_theta_max_deg.values()),
            "measured_theta_max_deg_by_source": dict(self.measured_theta_max_deg),
            "total_flux": total,
            "flux_beyond_measured_percent": 100.0 * self.beyond_fraction,
            "fitted_flux_beyond_measured_percent": 100.0 * self.fitted_beyond_fraction,
            "downward_flux_percent": 100.0,
            "zones": zones,
            "peak": {"intensity": intensity, "gamma_deg": gamma, "c_deg": c, "rotationally_symmetric": symmetric},
            "direct_ratios": {
                "room_index": list(ROOM_INDICES),
                "ratio": list(self.direct_ratios),
                "room": "square, the luminaires spread evenly over the ceiling, the work plane its floor",
            },
        }
        for kind in ("beam", "field"):
            out[f"{kind}_angle_deg"] = {plane: a.angle_deg for plane, a in self.angles[kind].items()}
            out[f"{kind}_half_angles_deg"] = {
                half: v for a in self.angles[kind].values() for half, v in a.half_angles_deg.items()
            }
            out[f"{kind}_angle_beyond_measured"] = any(a.beyond_measured for a in self.angles[kind].values())
        if self.near is not None:
            of_peak, local = self.near.largest_differences()
            out["near_field"] = {
                "distance_m": self.near.distance_m,
                "centre_m": list(self.near.centre_m),
                "half_width_m": float(self.near.x_m[-1] - self.near.centre_m[0]),
                "illuminance_units": {"W/sr": "W/m²"}.get(self.units, "relative per m²"),
                "peak_illuminance_array": float(np.max(self.near.array)),
                "peak_illuminance_point": float(np.max(self.near.point)),
                "max_difference_percent_of_peak": of_peak,
                "max_difference_percent_in_field": local,
            }
        return json_ready(out)


def summarize(
    model: LightModel,
    extrapolation: str = Extrapolation.FITTED,
    *,
    near_field_m: float | None = NEAR_FIELD_DISTANCE_M,
) -> Photometry:
    """The photometric summary of the whole light (:class:`Photometry`).

    Parameters
    ----------
    model : LightModel
    extrapolation : {"fitted", "none"}
        Beyond each source's measured θ: the fits' extrapolation, or zero (as the light files
        written with the same choice hold it).
    near_field_m : float or None
        The distance of the near-field plane, metres (None: no near field, the cheaper
        summary the light files' keywords need).

    Returns
    -------
    Photometry

    Notes
    -----
    The zones' flux is integrated source by source, each split at its measured θ
    (Gauss–Legendre, 32 nodes a segment, exact to rounding for smooth lobes); the peak is
    the largest value of the far field on a 0.1° × 2.5° grid; the beam and field angles are
    the crossings of 50 % and 10 % of that peak outward from each plane's maximum, on a
    0.05° grid interpolated linearly. The direct ratios are :func:`direct_ratios`.
    """
    extrapolation = Extrapolation(extrapolation).value
    measured, beyond = _zone_fluxes(model, ZONE_EDGES_DEG)
    fitted_beyond = float(beyond.sum())
    if extrapolation == Extrapolation.NONE:
        beyond = np.zeros_like(beyond)
    theta_max = {s.name: math.degrees(measured_theta_max(s)) for s in model.sources}
    peak = _peak(model, extrapolation)
    every = min(theta_max.values())
    angles: dict[str, dict[str, PlaneAngles]] = {"beam": {}, "field": {}}
    for halves in PLANES:
        for kind, found in _plane_angles(model, halves, peak[0], extrapolation, every).items():
            angles[kind][found.plane] = found
    near = None
    if near_field_m is not None:
        field = [a.angle_deg for a in angles["field"].values() if a.angle_deg is not None]
        half_angle = min(max(0.5 * max(field, default=120.0) + 5.0, 15.0), 70.0)
        half_width = near_field_m * math.tan(math.radians(half_angle))
        near = near_field(model, near_field_m, half_width, extrapolation=extrapolation)
    return Photometry(
        extrapolation,
        model.units,
        theta_max,
        ZONE_EDGES_DEG,
        measured,
        beyond,
        fitted_beyond,
        peak,
        angles,
        near,
        direct_ratios(model, extrapolation),
    )

"""From merged radiance to per-source samples of radiant intensity I_s(θ).

The camera's point spread is large (``measurement.md``: a 0.2 mm pinhole blurs a point
into a 38 px disc while five sources 4 mm apart image 7–12 px apart), so a pixel's chief
ray does not say which source its light came from. The estimate that counts unmixes: for
every source and position a *template* — the image that source alone would make at unit
intensity — and a variance-weighted non-negative least-squares solve for all sources'
intensities at once.

A template is built from exact specular paths, not from the chief-ray map: from the
source's centre, the path reflecting off the sphere into each point of the pinhole's rim
gives the blur's outline on the sensor (the aperture projected through the mirror, with
its astigmatism), and the set of those paths gives the solid angle the aperture subtends
at the source through the mirror. The blur is uniform inside the outline, convolved with
the source disc's own small image and with the Airy pattern of the aperture at the
channel's wavelength (its exact transfer function, band-limited below the pixel Nyquist
frequency). Its scale follows from radiometry alone::

    Σ_pixels rate = k f² / (A_pixel A_aperture) · F(α) · Ω · I

with ``k`` the camera's sensitivity (e⁻/s per unit radiance), ``f`` the sensor distance,
``F`` the ball's reflectance and ``Ω`` that solid angle.

The flux-conserving chief-ray cell sums of ``measurement.md`` step 4 are here too, as the
fast path for sources farther apart than the footprint of a pixel on the light plane.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
from scipy import fft as sfft
from scipy.linalg import solve_triangular
from scipy.optimize import nnls

from drivers.config_files import magnitude_problem, read_toml
from drivers.pose import Pose
from processing.trace import (
    ChiefRays,
    RigGeometry,
    _housing_blocks,
    conductor_reflectance,
    footprint_areas,
    trace_pixels,
)

CHANNEL_OF = {"R": 0, "G": 1, "B": 2}


class SourcesError(ValueError):
    """A layout or a run the source estimate cannot work with (one line)."""


# --- the layout of the sources on the light plane ------------------------------------------
@dataclass(frozen=True)
class Source:
    name: str
    centre: tuple[float, float]  # (u, v) on the light plane, metres
    radius: float  # emitting disc, metres


def load_layout(path: str | Path) -> list[Source]:
    """Sources from a TOML file: ``[[sources]]`` (or ``[[emitters]]``, the simulation's
    truth format) with ``name``, ``centre_m = [u, v]`` and ``radius_m``."""
    path = Path(path)
    data = read_toml(path, "layout file", SourcesError)
    entries = data.get("sources", data.get("emitters"))
    if not entries:
        raise SourcesError(f"{path}: no [[sources]] in the layout")
    out = []
    for i, entry in enumerate(entries):
        try:
            u, v = (float(x) for x in entry["centre_m"])
            radius = float(entry.get("radius_m", 0.5e-3))
        except (KeyError, TypeError, ValueError):
            raise SourcesError(f"{path}: sources[{i}].centre_m: needs [u, v] in metres") from None
        if not (math.isfinite(u) and math.isfinite(v)):  # inf and nan are TOML literals
            raise SourcesError(f"{path}: sources[{i}].centre_m: must be finite (got [{u}, {v}])")
        if not 0 < radius < math.inf:
            raise SourcesError(f"{path}: sources[{i}].radius_m: must be finite and > 0 (got {radius})")
        for name, value in (("centre_m", (u, v)), ("radius_m", radius)):
            if (problem := magnitude_problem(name, value)) is not None:
                raise SourcesError(f"{path}: sources[{i}].{name}: {problem}")
        out.append(Source(str(entry.get("name") or f"source-{i}"), (u, v), radius))
    return out


# --- specular paths -------------------------------------------------------------------------
def specular_points(
    sources: np.ndarray, targets: np.ndarray, centre: np.ndarray, radius: float, iterations: int = 60
) -> np.ndarray:
    """Points on a convex sphere where light from ``sources`` reflects to ``targets``.

    The normal at the reflection point bisects the directions to the source and to the
    target (the law of reflection); iterating that condition converges for a convex
    mirror seen from outside. Shapes broadcast: (..., 3).

    Compiled (:func:`_specular_kernel`): in NumPy a template's 121 paths took 60 rounds of
    a dozen small array operations, a millisecond of call overhead per template.
    """
    s, t = np.broadcast_arrays(np.asarray(sources, float) - centre, np.asarray(targets, float) - centre)
    shape = s.shape
    found = _specular_kernel(
        np.ascontiguousarray(s.reshape(-1, 3).T),
        np.ascontiguousarray(t.reshape(-1, 3).T),
        float(radius),
        int(iterations),
    )
    return found.T.reshape(shape) + centre


@numba.njit(cache=True, error_model="numpy")
def _specular_kernel(s: np.ndarray, t: np.ndarray, radius: float, iterations: int) -> np.ndarray:
    """:func:`specular_points` about the sphere's centre; ``s``, ``t`` and the result (3, N).

    Every point's update is ``p ← r · unit(unit(s - p) + unit(t - p))``, started from
    ``r · unit(unit(s) + unit(t))``. The loop runs over the points inside each round, so
    that it vectorises (independent square roots and divisions side by side).

    The update of a point depends on nothing but that point, so once every point's new
    value equals its last (a fixed point) or the one before (a two-cycle, which rounding
    can leave), the rest of the rounds would only repeat: the result of all
    ``iterations`` rounds is then read off by their parity, the same to the bit, after
    about 25 rounds instead of 60.
    """
    n = s.shape[1]
    p = np.empty((3, 3, n))  # the last three rounds, in rotation
    for i in range(n):
        ns = math.sqrt(s[0, i] * s[0, i] + s[1, i] * s[1, i] + s[2, i] * s[2, i])
        nt = math.sqrt(t[0, i] * t[0, i] + t[1, i] * t[1, i] + t[2, i] * t[2, i])
        mx, my, mz = s[0, i] / ns + t[0, i] / nt, s[1, i] / ns + t[1, i] / nt, s[2, i] / ns + t[2, i] / nt
        nm = math.sqrt(mx * mx + my * my + mz * mz)
        p[0, 0, i], p[0, 1, i], p[0, 2, i] = radius * (mx / nm), radius * (my / nm), radius * (mz / nm)
    for k in range(1, iterations + 1):
        cur, prev, prev2 = p[k % 3], p[(k - 1) % 3], p[(k - 2) % 3]
        for i in range(n):
            ax, ay, az = s[0, i] - prev[0, i], s[1, i] - prev[1, i], s[2, i] - prev[2, i]
            bx, by, bz = t[0, i] - prev[0, i], t[1, i] - prev[1, i], t[2, i] - prev[2, i]
            na = math.sqrt(ax * ax + ay * ay + az * az)
            nb = math.sqrt(bx * bx + by * by + bz * bz)
            mx, my, mz = ax / na + bx / nb, ay / na + by / nb, az / na + bz / nb
            nm = math.sqrt(mx * mx + my * my + mz * mz)
            cur[0, i], cur[1, i], cur[2, i] = radius * (mx / nm), radius * (my / nm), radius * (mz / nm)
        if k < 2:
            continue
        settled = True
        for i in range(n):
            same = cur[0, i] == prev[0, i] and cur[1, i] == prev[1, i] and cur[2, i] == prev[2, i]
            cycle = cur[0, i] == prev2[0, i] and cur[1, i] == prev2[1, i] and cur[2, i] == prev2[2, i]
            if not (same or cycle):
                settled = False
                break
        if settled:
            # Round ``iterations`` holds round k's value if their difference is even,
            # round k - 1's otherwise (the same value for a fixed point).
            return cur.copy() if (iterations - k) % 2 == 0 else prev.copy()
    return p[iterations % 3].copy()


def _polygon_area(points: np.ndarray) -> float:
    """Area of a simple polygon (N, 2) (the shoelace formula)."""
    return 0.5 * abs(_shoelace(np.ascontiguousarray(points, dtype=float)))


@numba.njit(cache=True, error_model="numpy")
def _shoelace(points: np.ndarray) -> float:
    """Twice the signed area of a polygon (N, 2): positive counter-clockwise. Compiled: a
    template asks for five, each a dozen NumPy calls on a hundred points."""
    total = 0.0
    n = points.shape[0]
    for i in range(n):
        j = (i + 1) % n
        total += points[i, 0] * points[j, 1] - points[i, 1] * points[j, 0]
    return total


@numba.njit(cache=True, error_model="numpy")
def _edge_lines(polygon: np.ndarray):
    """Outward unit normals (N, 2) and offsets (N,) of a convex polygon's edges: the
    points ``q`` inside are those with ``normal · q <= offset`` for every edge."""
    n = polygon.shape[0]
    order = np.arange(n) if _shoelace(polygon) >= 0 else np.arange(n)[::-1]  # counter-clockwise
    normals, offsets = np.empty((n, 2)), np.empty(n)
    for e in range(n):
        a, b = order[e], order[(e + 1) % n]
        nx, ny = polygon[b, 1] - polygon[a, 1], -(polygon[b, 0] - polygon[a, 0])
        length = math.sqrt(nx * nx + ny * ny)
        normals[e, 0], normals[e, 1] = nx / length, ny / length
        offsets[e] = normals[e, 0] * polygon[a, 0] + normals[e, 1] * polygon[a, 1]
    return normals, offsets


def _convex_coverage(polygon: np.ndarray, xs: np.ndarray, ys: np.ndarray, sample: float) -> np.ndarray:
    """Anti-aliased coverage of a convex polygon on a grid of samples ``sample`` wide.

    The signed distance to a convex polygon is the largest signed distance to its edges'
    lines; a linear ramp one sample wide across the edge is exact for straight edges.

    Only the samples in that ramp need the distance: the polygon shrunk by half a sample
    (coverage 1) and grown by half a sample (beyond it, 0) are convex too, and cut each
    row of the grid in one interval each, found from the edges' half-planes in
    O(rows × edges). The distances of the few samples between the two intervals are then
    computed exactly as for the whole grid (:func:`_coverage_kernel`).
    """
    normals, offsets = _edge_lines(np.ascontiguousarray(polygon, dtype=float))
    return _coverage_kernel(normals, offsets, np.asarray(xs, float), np.asarray(ys, float), float(sample))


@numba.njit(cache=True, error_model="numpy")
def _coverage_kernel(
    normals: np.ndarray, offsets: np.ndarray, xs: np.ndarray, ys: np.ndarray, sample: float
) -> np.ndarray:
    """The loop of :func:`_convex_coverage`, compiled: per row, the interval where every
    edge's ``n·(x, y) - offset`` is at most ``-half`` (coverage 1) and the one where it
    is at most ``+half`` (beyond it, coverage 0), and the ramp in between.

    A sample is in an interval ``[lo, hi]`` exactly when ``lo <= x <= hi``; the arithmetic
    is that of the vectorised form it replaces (``(bound + offset) - y n_y``, over ``n_x``),
    one row at a time instead of NumPy temporaries of rows × edges × columns.
    """
    half = 0.5 * sample
    # A margin far above rounding keeps every sample whose ramp value is not exactly 0
    # or 1 in the band that is computed in full.
    margin = 1e-6 * sample
    inner, outer = -half - margin, half + margin
    n_edges = offsets.size
    out = np.zeros((ys.size, xs.size))
    for r in range(ys.size):
        y = ys[r]
        in_lo, in_hi, out_lo, out_hi = -np.inf, np.inf, -np.inf, np.inf
        for e in range(n_edges):
            nx = normals[e, 0]
            if nx > 0:
                in_hi = min(in_hi, (inner + offsets[e] - y * normals[e, 1]) / nx)
                out_hi = min(out_hi, (outer + offsets[e] - y * normals[e, 1]) / nx)
            elif nx < 0:
                in_lo = max(in_lo, (inner + offsets[e] - y * normals[e, 1]) / nx)
                out_lo = max(out_lo, (outer + offsets[e] - y * normals[e, 1]) / nx)
            else:  # a horizontal edge: the whole row is on one side of it
                if inner + offsets[e] - y * normals[e, 1] < 0:
                    in_lo, in_hi = np.inf, -np.inf
                if outer + offsets[e] - y * normals[e, 1] < 0:
                    out_lo, out_hi = np.inf, -np.inf
        for c in range(xs.size):
            x = xs[c]
            if x < out_lo or x > out_hi:
                continue
            if in_lo <= x <= in_hi:
                out[r, c] = 1.0
                continue
            distance = -np.inf
            for e in range(n_edges):
                distance = max(distance, x * normals[e, 0] + y * normals[e, 1] - offsets[e])
            out[r, c] = min(1.0, max(0.0, 0.5 - distance / sample))
    return out


@functools.lru_cache(maxsize=48)
def _airy_otf(shape, pitch, aperture, sensor_distance, wavelength):
    """The aperture's diffraction transfer function on an ``rfft2`` grid (cached: a run's
    templates use a handful of grid sizes, three wavelengths). Read-only."""
    fy = sfft.fftfreq(shape[0], d=pitch)[:, None]
    fx = sfft.rfftfreq(shape[1], d=pitch)[None, :]
    rho = np.clip(np.hypot(fx, fy) * wavelength * sensor_distance / aperture, 0.0, 1.0)
    otf = (2.0 / math.pi) * (np.arccos(rho) - rho * np.sqrt(1.0 - rho * rho))
    otf.flags.writeable = False
    return otf


@functools.lru_cache(maxsize=6)
def _airy_psf(padded, pitch, aperture, sensor_distance, wavelength):
    """The aperture's point spread, periodic over ``padded`` pixels: the image whose
    circular convolution on that grid is the product with :func:`_airy_otf` (cached,
    read-only)."""
    psf = sfft.irfft2(_airy_otf((padded, padded), pitch, aperture, sensor_distance, wavelength), s=(padded, padded))
    psf.flags.writeable = False
    return psf


@functools.lru_cache(maxsize=48)
def _airy_kernel_spectrum(padded, pitch, aperture, sensor_distance, wavelength, reach, length):
    """``rfft2`` on a ``length`` square of the periodic point spread's offsets ``-reach``
    to ``reach`` (stored at 0 to ``2 reach``): what :func:`_diffract` multiplies by.

    Cached: a run's templates have a few sizes, and a position's five sources share them.
    Read-only.
    """
    offsets = np.arange(-reach, reach + 1) % padded
    kernel = _airy_psf(padded, pitch, aperture, sensor_distance, wavelength)[np.ix_(offsets, offsets)]
    spectrum = sfft.rfft2(kernel, s=(length, length))
    spectrum.flags.writeable = False
    return spectrum


def _diffract(
    geometric: np.ndarray,
    size: int,
    margin: int,
    padded: int,
    pitch: float,
    aperture: float,
    sensor_distance: float,
    wavelengths,
) -> np.ndarray:
    """``geometric`` (n × n, placed ``margin`` in from the corner of a ``size`` square)
    convolved with each channel's Airy pattern as the OTF on a ``padded`` grid does it;
    the ``size`` square back, (channels, size, size).

    The diffraction the templates model is ``irfft2(rfft2(image, s) * otf, s)[:size, :size]``
    with ``s`` = ``padded`` (4× the patch: the pattern's far tails wrap around that far
    away). That is a circular convolution with the ``padded``-periodic point spread, and the
    output square only ever reads that point spread at offsets ``-reach..reach``,
    ``reach = n - 1 + margin``. So the same numbers come from a linear convolution with
    that piece of it, done on a ``length ≥ 2 reach + 1`` grid whose wrap-around misses the
    output: a grid about 2.8× smaller per axis, and the piece's transform is cached per
    size and channel. The transforms go one axis at a time so that the rows known to be
    zero (beyond ``n``) are not transformed, nor the rows the result does not need. The
    numbers agree with the 4×-padded product to rounding (1e-15 of the peak).
    """
    n = geometric.shape[0]
    reach = n - 1 + margin
    length = sfft.next_fast_len(2 * reach + 1)
    spectrum = sfft.fft(sfft.rfft(geometric, n=length, axis=1), n=length, axis=0)  # (length, length // 2 + 1)
    out = np.empty((len(wavelengths), size, size))
    for c, wavelength in enumerate(wavelengths):  # one channel at a time, in place: less memory to touch
        kernel = _airy_kernel_spectrum(padded, pitch, aperture, sensor_distance, float(wavelength), reach, length)
        # Output pixel y reads the full linear convolution at y + n - 1 (offset -reach there).
        back = sfft.ifft(spectrum * kernel, axis=0, overwrite_x=True)[n - 1 : n - 1 + size]
        out[c] = sfft.irfft(back, n=length, axis=1)[:, n - 1 : n - 1 + size]
    return out


def _convolve_same(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``fftconvolve(image, kernel, mode="same")`` for a square image and an odd square kernel.

    "Same" is the middle of the full convolution, from ``half = k // 2`` on; a circular
    convolution on ``length ≥ n + half`` wraps only the full convolution's tail beyond
    ``n + k - 2`` onto indices below ``half``, outside that middle: a smaller grid than
    SciPy's ``n + k - 1``. The transforms go one axis at a time so that the kernel's zero
    rows (all but ``k`` of ``length``) are not transformed, nor the rows not returned.
    """
    n, k = image.shape[0], kernel.shape[0]
    half = k // 2
    length = sfft.next_fast_len(n + half, real=True)
    product = sfft.fft(sfft.rfft(image, n=length, axis=1), n=length, axis=0)
    product *= sfft.fft(sfft.rfft(kernel, n=length, axis=1), n=length, axis=0)
    back = sfft.ifft(product, axis=0, overwrite_x=True)[half : half + n]
    return sfft.irfft(back, n=length, axis=1)[:, half : half + n]


# --- templates --------------------------------------------------------------------------------
@dataclass
class Template:
    """One source's image at one position, per unit radiant intensity (1 W/sr).

    ``image`` is (3, h, w): the electron rate per second each channel's pixels would see
    in the patch whose top-left pixel is (row0, col0).
    """

    source: str
    row0: int
    col0: int
    image: np.ndarray
    theta: float
    phi: float
    alpha: float
    fresnel: np.ndarray
    solid_angle: float
    image_centre: tuple[float, float]  # chief ray's pixel (col, row)
    blur_radius_px: float


@dataclass
class TemplateBuilder:
    """Templates of sources on the light plane for a rig (``measurement.md`` step 3)."""

    geometry: RigGeometry
    sensitivity: float
    diffraction: bool = True
    rim_points: int = 96
    oversample: int = 4
    airy_margin_px: int = 32

    def build(self, source: Source, light_pose: Pose) -> Template | None:
        """The source's template, or None if the ball does not show it to the camera."""
        g = self.geometry
        rot, origin = light_pose.rotation, light_pose.position
        q = origin + rot @ np.array([source.centre[0], source.centre[1], 0.0])
        pinhole = g.camera_centre
        # Every specular path of the template in one batch: the chief path (source centre
        # to pinhole), the pinhole's rim, and the source disc's outline.
        angles = np.linspace(0.0, 2.0 * math.pi, self.rim_points, endpoint=False)
        rim_cam = np.stack(
            [g.aperture_radius * np.cos(angles), g.aperture_radius * np.sin(angles), np.zeros_like(angles)], -1
        )
        rim = pinhole + rim_cam @ g.R  # camera -> rig
        disc_angles = np.linspace(0.0, 2.0 * math.pi, 24, endpoint=False)
        disc = origin + (
            np.stack(
                [
                    source.centre[0] + source.radius * np.cos(disc_angles),
                    source.centre[1] + source.radius * np.sin(disc_angles),
                    np.zeros_like(disc_angles),
                ],
                -1,
            )
            @ rot.T
        )
        m = self.rim_points
        starts = np.concatenate([q[None, :], np.broadcast_to(q, rim.shape), disc])
        ends = np.concatenate([pinhole[None, :], rim, np.broadcast_to(pinhole, disc.shape)])
        found = specular_points(starts, ends, g.ball_centre, g.ball_radius)
        p0, paths, disc_paths = found[0], found[1 : 1 + m], found[1 + m :]
        emit = (p0 - q) / np.linalg.norm(p0 - q)
        local = rot.T @ emit
        if local[2] <= 0.0:
            return None  # the ball is behind the light plane
        if _housing_blocks(pinhole[None, :], p0[None, :], light_pose, g.housing_radius, g.housing_depth)[0]:
            return None
        normal = (p0 - g.ball_centre) / g.ball_radius
        cos_alpha = float(np.dot(normal, (q - p0) / np.linalg.norm(q - p0)))
        fresnel = conductor_reflectance(np.array([cos_alpha]), g.n, g.k)[0]
        # Where the rim's specular paths land on the sensor.
        outline = self._sensor_points(paths, rim_cam)
        # The solid angle of those paths at the source (a small polygon of directions).
        directions = (paths - q) / np.linalg.norm(paths - q, axis=-1, keepdims=True)
        axis = directions.mean(axis=0)
        axis /= np.linalg.norm(axis)
        e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        tangent = np.stack([directions @ e1, directions @ e2], -1) / (directions @ axis)[:, None]
        solid_angle = _polygon_area(tangent)
        # The source disc's own image through the pinhole's centre.
        disc_image = g.project(disc_paths)
        centre_px = g.project(p0[None, :])[0]
        image = self._render(outline, disc_image - centre_px, centre_px)
        top, left, pixels = image
        scale = self.sensitivity * g.sensor_distance**2 / (g.pitch**2 * math.pi * g.aperture_radius**2) * solid_angle
        pixels = pixels * (scale * fresnel)[:, None, None]
        theta = float(math.acos(np.clip(local[2], -1.0, 1.0)))
        phi = float(math.atan2(local[1], local[0]))
        blur = float(np.sqrt(_polygon_area(outline) / math.pi))
        return Template(
            source.name,
            top,
            left,
            pixels,
            theta,
            phi,
            float(math.acos(min(1.0, cos_alpha))),
            fresnel,
            solid_angle,
            (float(centre_px[0]), float(centre_px[1])),
            blur,
        )

    def _sensor_points(self, paths: np.ndarray, rim_cam: np.ndarray) -> np.ndarray:
        """Where the rays from reflection points through rim points land, in pixels.

        A thin lens of focal length F images an object point P (distance u) at
        P' = -P v/u, v = 1/(1/F - 1/u); the ray through the rim point a heads for P' and
        meets the sensor at a + (P' - a) f / v. With 1/F = 0 this is the pinhole's
        straight line.
        """
        g = self.geometry
        p_cam = paths @ g.R.T + g.t
        u = p_cam[:, 2]
        v = 1.0 / (g.inverse_focal - 1.0 / u)
        image = np.stack([-p_cam[:, 0] * v / u, -p_cam[:, 1] * v / u, -v], axis=-1)
        sensor = rim_cam + (image - rim_cam) * (g.sensor_distance / v)[:, None]  # on the plane z = -f
        return np.stack([g.K[0, 2] - sensor[:, 0] / g.pitch, g.K[1, 2] - sensor[:, 1] / g.pitch], -1)

    def _render(self, outline: np.ndarray, disc: np.ndarray, centre: np.ndarray):
        g, os_ = self.geometry, self.oversample
        reach = float(np.max(np.linalg.norm(outline - centre, axis=1)) + np.max(np.linalg.norm(disc, axis=1)) + 2.0)
        half = int(math.ceil(reach))
        c0, r0 = int(round(centre[0])) - half, int(round(centre[1])) - half
        n = 2 * half + 1
        sub = 1.0 / os_
        xs = c0 - 0.5 + (np.arange(n * os_) + 0.5) * sub
        ys = r0 - 0.5 + (np.arange(n * os_) + 0.5) * sub
        blur = _convex_coverage(outline, xs, ys, sub)
        blur /= blur.sum()
        # The source's disc image, centred, as a kernel on the same fine grid.
        k_half = int(math.ceil(np.max(np.abs(disc)) * os_)) + 2
        kx = (np.arange(-k_half, k_half + 1)) * sub
        kernel = _convex_coverage(disc, kx, kx, sub) if _polygon_area(disc) > (0.25 * sub) ** 2 else None
        if kernel is not None and kernel.sum() > 0:
            blur = _convolve_same(blur, kernel / kernel.sum())
        geometric = blur.reshape(n, os_, n, os_).sum(axis=(1, 3))
        margin = self.airy_margin_px if self.diffraction else 0
        size = n + 2 * margin
        if self.diffraction:
            padded = sfft.next_fast_len(4 * size, real=True)
            channels = _diffract(
                geometric,
                size,
                margin,
                padded,
                float(g.pitch),
                float(2 * g.aperture_radius),
                float(g.sensor_distance),
                [float(g.wavelengths[c]) for c in range(3)],
            )
        else:
            channels = np.zeros((3, size, size))
            channels[:, margin : margin + n, margin : margin + n] = geometric
        return r0 - margin, c0 - margin, channels


# --- unmixing -------------------------------------------------------------------------------------
@dataclass
class PositionEstimate:
    """Intensities of every source at one position, per channel, with uncertainties."""

    index: int
    intensity: np.ndarray  # (n_sources, 3) W/sr (relative without calibration)
    sigma: np.ndarray  # (n_sources, 3)
    theta: np.ndarray  # (n_sources,)
    phi: np.ndarray
    visible: np.ndarray  # (n_sources,) bool
    templates: list = field(default_factory=list)
    residual_rms: np.ndarray = field(default_factory=lambda: np.zeros(3))  # weighted, per channel


def cfa_channels(pattern: str, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    tile = np.array(
        [[CHANNEL_OF[pattern[0]], CHANNEL_OF[pattern[1]]], [CHANNEL_OF[pattern[2]], CHANNEL_OF[pattern[3]]]]
    )
    return tile[rows % 2, cols % 2]


def unmix_position(
    index: int,
    rate_e: np.ndarray,
    variance_e: np.ndarray,
    usable: np.ndarray,
    cfa_pattern: str,
    builder: TemplateBuilder,
    sources: list[Source],
    light_pose: Pose,
    *,
    region: str = "intersection",
) -> PositionEstimate:
    """Variance-weighted NNLS for every source's intensity at one position.

    ``rate_e`` and ``variance_e`` are the merged mosaic in e⁻/s and (e⁻/s)², as arrays or
    anything with a ``shape`` that gives arrays when indexed (only a window is read:
    ``processing.pipeline.ElectronRates`` converts just that); ``usable`` masks pixels
    with a valid, unsaturated estimate. ``region``: fit where every template
    is whole (``"intersection"``, exact), or over all of them (``"union"``, for many
    candidates spread wide, at the cost of cutting the far diffraction tails).
    """
    n = len(sources)
    templates = [builder.build(s, light_pose) for s in sources]
    visible = np.array([t is not None for t in templates])
    intensity = np.full((n, 3), np.nan)
    sigma = np.full((n, 3), np.nan)
    theta = np.array([t.theta if t else np.nan for t in templates])
    phi = np.array([t.phi if t else np.nan for t in templates])
    residual = np.full(3, np.nan)
    shown = [i for i in range(n) if visible[i]]
    if not shown:
        return PositionEstimate(index, intensity, sigma, theta, phi, visible, templates, residual)
    h, w = rate_e.shape
    # Fit where every template is whole: outside its patch a template is cut to zero
    # while the data still holds its diffraction tail.
    pick_lo, pick_hi = (max, min) if region == "intersection" else (min, max)
    top = max(0, pick_lo(templates[i].row0 for i in shown))
    left = max(0, pick_lo(templates[i].col0 for i in shown))
    bottom = min(h, pick_hi(templates[i].row0 + templates[i].image.shape[1] for i in shown))
    right = min(w, pick_hi(templates[i].col0 + templates[i].image.shape[2] for i in shown))
    if bottom <= top or right <= left:
        return PositionEstimate(index, intensity, sigma, theta, phi, np.zeros(n, bool), templates, residual)
    rows, cols = np.mgrid[top:bottom, left:right]
    channel = cfa_channels(cfa_pattern, rows, cols)
    columns = np.zeros((len(shown), bottom - top, right - left))
    for k, i in enumerate(shown):
        _place(templates[i], (top, bottom, left, right), channel, columns[k])
    data = rate_e[top:bottom, left:right]
    var = variance_e[top:bottom, left:right]
    ok = usable[top:bottom, left:right] & np.isfinite(data) & np.isfinite(var) & (var > 0)
    for c in range(3):
        sel = ok & (channel == c)
        if np.count_nonzero(sel) < 4 * len(shown):
            continue
        weight = 1.0 / np.sqrt(var[sel])
        a = columns[:, sel].T * weight[:, None]
        b = data[sel] * weight
        gram = a.T @ a
        solution = _nnls(a, b, gram, maxiter=50 * len(shown))
        try:
            cov = np.linalg.inv(gram)
            err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        except np.linalg.LinAlgError:
            err = np.full(len(shown), np.nan)
        intensity[shown, c] = solution
        sigma[shown, c] = err
        dof = max(1, a.shape[0] - len(shown))
        residual[c] = float(np.sqrt(np.sum((a @ solution - b) ** 2) / dof))
    return PositionEstimate(index, intensity, sigma, theta, phi, visible, templates, residual)


def _place(template: Template, window: tuple[int, int, int, int], channel: np.ndarray, out: np.ndarray) -> None:
    """Write the part of ``template`` inside ``window`` (top, bottom, left, right) into ``out``
    (the window's shape), each photosite taking its own ``channel``'s template."""
    top, bottom, left, right = window
    t = template
    r_lo, c_lo = max(t.row0, top), max(t.col0, left)
    r_hi, c_hi = min(t.row0 + t.image.shape[1], bottom), min(t.col0 + t.image.shape[2], right)
    if r_hi <= r_lo or c_hi <= c_lo:
        return
    patch = t.image[:, r_lo - t.row0 : r_hi - t.row0, c_lo - t.col0 : c_hi - t.col0]
    ch = channel[r_lo - top : r_hi - top, c_lo - left : c_hi - left]
    out[r_lo - top : r_hi - top, c_lo - left : c_hi - left] = np.take_along_axis(patch, ch[None], 0)[0]


def _nnls(a: np.ndarray, b: np.ndarray, gram: np.ndarray, maxiter: int) -> np.ndarray:
    """``argmin ||a x - b||, x >= 0``, solved on the small square system.

    With ``gram = aᵀa = L Lᵀ`` (Cholesky), ``||a x - b||² = ||Lᵀx - L⁻¹aᵀb||² + const``: the
    same problem with as many rows as unknowns, so the active-set solver's work no longer
    grows with the pixels (a few hundred candidate sources over 10⁴–10⁵ pixels: seconds
    become milliseconds; the solutions agree to 1e-12 of the largest). A matrix too
    ill-conditioned for Cholesky is solved as given.
    """
    try:
        lower = np.linalg.cholesky(gram)
    except np.linalg.LinAlgError:
        return nnls(a, b, maxiter=maxiter)[0]
    rhs = solve_triangular(lower, a.T @ b, lower=True)
    return nnls(lower.T, rhs, maxiter=maxiter)[0]


# --- the fast path: flux-conserving chief-ray cell sums ------------------------------------------
def cell_sums(
    rate_e: np.ndarray,
    usable: np.ndarray,
    geometry: RigGeometry,
    sensitivity: float,
    sources: list[Source],
    light_pose: Pose,
    cell_radius: float,
    cfa_pattern: str = "RGGB",
) -> np.ndarray:
    """``I_c ≈ Σ L_i A_i cos θ_i`` over the pixels whose chief ray lands within ``cell_radius``
    of each source (``measurement.md`` step 4), per channel: (n_sources, 3).

    Only the lit pixels in :func:`cell_pixel_boxes` are traced (a few hundred instead of
    every lit pixel of the frame, ~10⁵, which took 35 ms a position): a superset of those
    whose chief ray can land in a cell, so the same pixels pass the exact test below, in
    the same (row-major) order. The trace is per pixel, so each pixel's numbers do not
    depend on which others are traced with it, and the sums are those of tracing every
    lit pixel (to the bit on the benchmark run's 66 positions). Without such boxes every
    lit pixel is traced.
    """
    boxes = cell_pixel_boxes(geometry, light_pose, sources, cell_radius, rate_e.shape)
    if boxes is None:
        rows, cols = np.nonzero(usable & (rate_e[:, :] > 0))  # [:, :]: an array, or a lazy view of one
    else:
        width = rate_e.shape[1]
        flat = [(np.arange(r0, r1)[:, None] * width + np.arange(c0, c1)[None, :]).ravel() for r0, r1, c0, c1 in boxes]
        rows, cols = np.divmod(np.unique(np.concatenate(flat)) if flat else np.zeros(0, np.intp), width)
        lit = usable[rows, cols] & (rate_e[rows, cols] > 0)
        rows, cols = rows[lit], cols[lit]
    if rows.size == 0:
        return np.zeros((len(sources), 3))
    rays = trace_pixels(geometry, light_pose, cols.astype(float), rows.astype(float))
    out = np.zeros((len(sources), 3))
    near = np.zeros(rays.valid.shape, bool)
    for s in sources:
        near |= np.hypot(rays.u - s.centre[0], rays.v - s.centre[1]) <= cell_radius
    keep = rays.valid & near
    if not np.any(keep):
        return out
    # The kept pixels' rays: the trace is per pixel, so a subset of it is their trace.
    sub_rays = ChiefRays(
        **{
            name: value[keep] if isinstance(value, np.ndarray) and value.shape[:1] == keep.shape else value
            for name, value in vars(rays).items()
        }
    )
    area = footprint_areas(geometry, light_pose, sub_rays)
    channel = cfa_channels(cfa_pattern, rows[keep], cols[keep])
    for i, s in enumerate(sources):
        inside = np.hypot(sub_rays.u - s.centre[0], sub_rays.v - s.centre[1]) <= cell_radius
        inside &= np.isfinite(area)
        for c in range(3):
            sel = inside & (channel == c)
            radiance = rate_e[rows[keep][sel], cols[keep][sel]] / (
                sensitivity * sub_rays.fresnel[sel, c] * sub_rays.cos4[sel]
            )
            # Each channel samples only its own photosites: scale by the share of the CFA.
            share = {0: 4.0, 1: 2.0, 2: 4.0}[c]
            out[i, c] = share * np.sum(radiance * area[sel] * np.cos(sub_rays.theta[sel]))
    return out


def cell_pixel_boxes(
    geometry: RigGeometry,
    light_pose: Pose,
    sources: list[Source],
    cell_radius: float,
    shape: tuple[int, int],
    margin_px: float = 1.0,
) -> list[tuple[int, int, int, int]] | None:
    """Per source, a box of pixels ``(row0, row1, col0, col1)`` (ends excluded, within
    ``shape``) holding every pixel whose chief ray lands within ``cell_radius`` of it;
    None when such boxes cannot be vouched for (then every pixel is a candidate).

    Why the boxes hold every such pixel: the chief-ray map from pixels to the light plane
    is continuous and one-to-one where rays reach the plane (a point of the plane has one
    specular point on a convex ball that both it and the pinhole see), so the pixels of
    a cell are those inside the image of the cell's circle, and a box holding that closed
    curve holds them. The curve is found backwards, by exact specular paths from points
    of the circle to the pinhole, and each point is checked forwards: the chief ray of the
    pixel found must land back on the circle point (to 1e-6 of the radius: the iteration
    converged). The points are spaced at most ``gap`` ≤ 0.5 px apart along the curve,
    and an arc that short on a smooth curve stays within ``gap`` of its ends, so the
    points' bounding box grown by ``gap + margin_px`` holds the whole curve with room
    to spare; its rows and columns are then rounded outwards to whole pixels (centres at
    integers, as :func:`processing.trace.trace_pixels` takes them).

    None when the ball is not wholly in front of the light plane (the map is not one-to-one
    there) and of the camera, when a circle point does not check out, or when the boxes
    are so large that tracing every pixel is as cheap.
    """
    height, width = shape
    rot, origin = light_pose.rotation, light_pose.position
    g = geometry
    in_front_of_light = float((g.ball_centre - origin) @ rot[:, 2]) > g.ball_radius
    in_front_of_camera = float((g.R @ (g.ball_centre - g.camera_centre))[2]) > g.ball_radius  # projections hold
    if not (in_front_of_light and in_front_of_camera and sources and 0.0 <= cell_radius < math.inf):
        return None
    centres = np.array([s.centre for s in sources], float)  # (S, 2)
    count = 64
    while True:
        angles = np.linspace(0.0, 2.0 * math.pi, count, endpoint=False)
        circle = centres[:, None, :] + cell_radius * np.stack([np.cos(angles), np.sin(angles)], -1)[None]  # (S, n, 2)
        local = np.concatenate([circle, np.zeros(circle.shape[:2] + (1,))], axis=-1)
        points = origin + local @ rot.T
        found = specular_points(points, g.camera_centre, g.ball_centre, g.ball_radius)
        pixels = g.project(found.reshape(-1, 3)).reshape(len(sources), count, 2)
        if not np.all(np.isfinite(pixels)):
            return None
        gap = float(np.max(np.linalg.norm(pixels - np.roll(pixels, 1, axis=1), axis=-1)))
        if gap <= 0.5:
            break
        if count >= 8192:
            return None  # a cell spanning thousands of pixels: trace them all
        count = min(8192, int(math.ceil(count * gap / 0.4)))
    rays = trace_pixels(g, light_pose, pixels[..., 0].ravel(), pixels[..., 1].ravel())
    miss = np.hypot(rays.u - circle[..., 0].ravel(), rays.v - circle[..., 1].ravel())
    if not (np.all(rays.reaches_plane) and np.all(miss <= 1e-6 * cell_radius)):
        return None
    grow = gap + margin_px
    boxes, total = [], 0
    for p in pixels:
        r0 = max(0, int(math.floor(p[:, 1].min() - grow)))
        r1 = min(height, int(math.ceil(p[:, 1].max() + grow)) + 1)
        c0 = max(0, int(math.floor(p[:, 0].min() - grow)))
        c1 = min(width, int(math.ceil(p[:, 0].max() + grow)) + 1)
        if r1 > r0 and c1 > c0:
            boxes.append((r0, r1, c0, c1))
            total += (r1 - r0) * (c1 - c0)
    return boxes if total <= height * width // 8 else None


# --- the layout from the data -----------------------------------------------------------------
def lit_box(
    rate: np.ndarray, ok: np.ndarray, pose: Pose, geometry: RigGeometry, core_fraction: float = 0.2
) -> tuple[float, float, float, float] | None:
    """(u0, u1, v0, v1) on the light plane of the chief rays of one position's brightest
    pixels (above ``core_fraction`` of its peak); None if nothing is lit."""
    lit = ok & np.isfinite(rate) & (rate > core_fraction * np.nanmax(np.where(ok, rate, 0.0)))
    rows, cols = np.nonzero(lit)
    if rows.size == 0:
        return None
    rays = trace_pixels(geometry, pose, cols.astype(float), rows.astype(float))
    if not np.any(rays.valid):
        return None
    u, v = rays.u[rays.valid], rays.v[rays.valid]
    return (float(u.min()), float(u.max()), float(v.min()), float(v.max()))


def candidate_grid(boxes, *, spacing: float = 1.5e-3, margin: float = 3e-3):
    """Candidate point sources every ``spacing`` over the union of ``boxes`` (None ignored)
    plus ``margin``: (candidates, us, vs), the candidates row by row (v) along u."""
    boxes = [b for b in boxes if b is not None]
    if not boxes:
        raise SourcesError("no light in the data to find sources in")
    u0, u1 = min(b[0] for b in boxes) - margin, max(b[1] for b in boxes) + margin
    v0, v1 = min(b[2] for b in boxes) - margin, max(b[3] for b in boxes) + margin
    us = np.arange(math.floor(u0 / spacing), math.ceil(u1 / spacing) + 1) * spacing
    vs = np.arange(math.floor(v0 / spacing), math.ceil(v1 / spacing) + 1) * spacing
    candidates = [
        Source(f"c{i}-{j}", (float(u), float(v)), 0.25 * spacing) for j, v in enumerate(vs) for i, u in enumerate(us)
    ]
    return candidates, us, vs


def candidate_strength(
    rate: np.ndarray,
    variance: np.ndarray,
    ok: np.ndarray,
    pose: Pose,
    builder: TemplateBuilder,
    candidates: list[Source],
    cfa_pattern: str,
) -> np.ndarray:
    """Every candidate's unmixed intensity at one position, over the largest (so 1 at the
    strongest; zeros if none lights up). On one BLAS thread, as in a Dask worker: this is
    where :func:`refine_layout` starts, and it must start from the same bits wherever it runs."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        estimate = unmix_position(-1, rate, variance, ok, cfa_pattern, builder, candidates, pose, region="union")
    values = np.nan_to_num(np.nanmean(estimate.intensity, axis=1))
    return values / values.max() if values.max() > 0 else np.zeros(len(candidates))


def sources_from_strength(
    strength: np.ndarray,
    us: np.ndarray,
    vs: np.ndarray,
    *,
    spacing: float = 1.5e-3,
    threshold: float = 0.05,
    min_separation: float = 2e-3,
) -> list[Source]:
    """The local maxima of the candidates' summed strength, refined and merged into sources."""
    grid = np.asarray(strength, float).reshape(len(vs), len(us))
    found = []
    peak = grid.max()
    if peak <= 0:
        raise SourcesError("no source stands out of the candidate grid")
    for j in range(len(vs)):
        for i in range(len(us)):
            value = grid[j, i]
            window = grid[max(0, j - 1) : j + 2, max(0, i - 1) : i + 2]
            if value < threshold * peak or value < window.max():
                continue
            jj, ii = np.mgrid[max(0, j - 1) : j + 2, max(0, i - 1) : i + 2]
            u = float((window * us[ii]).sum() / window.sum())
            v = float((window * vs[jj]).sum() / window.sum())
            found.append((u, v, float(window.sum())))
    # Peaks closer than the resolution are one source whose strength the grid shared out.
    merged: list[list[float]] = []
    for u, v, w in sorted(found, key=lambda p: -p[2]):
        for m in merged:
            if math.hypot(u - m[0] / m[2], v - m[1] / m[2]) < min_separation:
                m[0] += u * w
                m[1] += v * w
                m[2] += w
                break
        else:
            merged.append([u * w, v * w, w])
    return [Source(f"source-{k}", (m[0] / m[2], m[1] / m[2]), 0.5 * spacing) for k, m in enumerate(merged)]


# --- the layout refined: continuous positions, sources added while the data ask for them ----------------
@dataclass(frozen=True)
class LayoutData:
    """One position's merged mosaic for the layout search: e⁻/s, (e⁻/s)², usable pixels, light pose."""

    rate: np.ndarray
    variance: np.ndarray
    usable: np.ndarray
    pose: Pose


@dataclass
class LayoutFit:
    """The sources :func:`refine_layout` settled on, and how well they explain the data.

    ``refined`` is False when no refinement could be made (``message`` says why) and
    ``sources`` are then the first guess unchanged; ``chi2`` and ``pixels`` are the
    weighted squared residual over the fitted pixels and their count (χ²/pixels ≈ 1 when
    the templates explain the data to its noise); ``steps`` holds (sources, χ²) after each
    accepted step.
    """

    sources: list[Source]
    refined: bool
    message: str
    chi2: float = float("nan")
    pixels: int = 0
    steps: list[tuple[int, float]] = field(default_factory=list)


def seeds_from_strength(
    strength: np.ndarray, us: np.ndarray, vs: np.ndarray, *, threshold: float = 0.05
) -> list[tuple[float, float]]:
    """The candidates of the grid that took at least ``threshold`` of the strongest one's
    strength: where the unmixing put light, so where a source the local maxima missed can be."""
    grid = np.asarray(strength, float).reshape(len(vs), len(us))
    peak = grid.max(initial=0.0)
    if peak <= 0:
        return []
    j, i = np.nonzero(grid >= threshold * peak)
    order = np.argsort(-grid[j, i], kind="stable")
    return [(float(us[i[k]]), float(vs[j[k]])) for k in order]


class _LayoutProblem:
    """The weighted residual of the data against templates of point sources at free (u, v),
    their intensities solved for (NNLS, per position and channel) at every evaluation: the
    positions are the only parameters left (variable projection, Golub & Pereyra 1973).

    Pixels are fixed once (a least-squares residual keeps its length): at each position
    the window where every first-guess template is whole, less ``inset_px`` on each side,
    with templates given ``margin_px`` of diffraction around their core (plus the spread of
    the first guess's images) so that the window holds every source's light and most of
    its diffraction; outside a template's patch the data still hold its diffraction tail,
    which a cut template would call a residual (at the true layout the residual RMS was
    5-9 σ over the union of 32 px patches, 1.03 σ where every template is whole).
    """

    def __init__(
        self,
        data: list[LayoutData],
        builder: TemplateBuilder,
        cfa_pattern: str,
        first: list[Source],
        margin_px: int,
        inset_px: int,
    ):
        from dataclasses import replace

        # Every template must cover the whole window, so each is given ``margin_px`` beyond the
        # spread of the first guess's images as well (the window is the patches' intersection).
        # A wider diffraction margin only pads a template's patch (``TemplateBuilder._render``), so
        # the windows follow from the first guess's templates built once, at the builder's margin.
        first_built = [[t for t in (builder.build(s, item.pose) for s in first) if t is not None] for item in data]
        spread = max(
            [max(np.ptp([t.row0 for t in built]), np.ptp([t.col0 for t in built])) for built in first_built if built],
            default=0,
        )
        self.builder = replace(builder, airy_margin_px=max(builder.airy_margin_px, margin_px + int(spread)))
        pad = self.builder.airy_margin_px - builder.airy_margin_px if builder.diffraction else 0
        self.windows = []
        self._columns: dict[tuple, np.ndarray] = {}
        for item, built in zip(data, first_built, strict=True):
            if not built:
                continue
            h, w = item.rate.shape
            top = max(0, max(t.row0 for t in built) - pad + inset_px)
            left = max(0, max(t.col0 for t in built) - pad + inset_px)
            bottom = min(h, min(t.row0 + t.image.shape[1] for t in built) + pad - inset_px)
            right = min(w, min(t.col0 + t.image.shape[2] for t in built) + pad - inset_px)
            if bottom - top < 8 or right - left < 8:
                continue
            rows, cols = np.mgrid[top:bottom, left:right]
            channel = cfa_channels(cfa_pattern, rows, cols)
            rate = np.asarray(item.rate[top:bottom, left:right], float)
            var = np.asarray(item.variance[top:bottom, left:right], float)
            ok = (
                np.asarray(item.usable[top:bottom, left:right], bool) & np.isfinite(rate) & np.isfinite(var) & (var > 0)
            )
            picks = [ok & (channel == c) for c in range(3)]
            weights = [1.0 / np.sqrt(var[pick]) for pick in picks]
            self.windows.append(
                (
                    item.pose,
                    (top, bottom, left, right),
                    channel,
                    picks,
                    weights,
                    [rate[pick] * weight for pick, weight in zip(picks, weights, strict=True)],
                )
            )
        self.pixels = sum(int(np.count_nonzero(pick)) for window in self.windows for pick in window[3])

    def _column(self, p: int, u: float, v: float, radius: float) -> list[np.ndarray]:
        """The template of a unit source at (u, v) over window ``p``: per channel, its values
        at that channel's fitted photosites."""
        key = (p, u, v, radius)
        column = self._columns.get(key)
        if column is not None:
            return column
        pose, window, channel, picks, *_ = self.windows[p]
        top, bottom, left, right = window
        column = np.zeros((bottom - top, right - left))
        template = self.builder.build(Source("trial", (u, v), radius), pose)
        if template is not None:
            _place(template, window, channel, column)
        column = [column[pick] for pick in picks]
        if len(self._columns) >= 64 * len(self.windows):  # a Jacobian's worth several times over; oldest out
            for old in list(self._columns)[: len(self._columns) // 2]:
                del self._columns[old]
        self._columns[key] = column
        return column

    def set_aperture(self, radius: float) -> None:
        """Build the templates through an aperture of ``radius`` from now on (the pixels stay)."""
        from dataclasses import replace

        self.set_geometry(replace(self.builder.geometry, aperture_radius=radius))

    def set_geometry(self, geometry) -> None:
        """Build the templates through ``geometry`` from now on (the pixels stay)."""
        from dataclasses import replace

        self.builder = replace(self.builder, geometry=geometry)
        self._columns.clear()

    def solve(self, centres: np.ndarray, radius) -> tuple[np.ndarray, np.ndarray]:
        """(weighted residuals, intensities (positions, 3, sources)) for discs of ``radius`` (one
        for all, or one per source) at ``centres`` (S, 2), in metres."""
        residuals, intensities = [], np.zeros((len(self.windows), 3, len(centres)))
        for p, (_, _, _, _, weights, targets) in enumerate(self.windows):
            radii = np.broadcast_to(np.asarray(radius, float), (len(centres),))  # one radius, or each source's
            columns = [self._column(p, float(u), float(v), float(r)) for (u, v), r in zip(centres, radii, strict=True)]
            for c in range(3):
                a = np.stack([column[c] for column in columns], axis=1) * weights[c][:, None]
                gram = a.T @ a
                # A source the ball does not show here has a zero column: a ridge keeps Cholesky whole.
                ridge = 1e-12 * max(float(np.trace(gram)), 1e-300) * np.eye(len(columns))
                x = _nnls(a, targets[c], gram + ridge, maxiter=100 * len(columns))
                intensities[p, c] = x
                residuals.append(a @ x - targets[c])
        return np.concatenate(residuals), intensities

    def chi2(self, centres: np.ndarray, radius: float) -> float:
        r, _ = self.solve(centres, radius)
        return float(r @ r)

    def light(self, centres: np.ndarray, radius: float) -> np.ndarray:
        """Each source's intensity summed over the positions and channels (0: it explains nothing)."""
        return self.solve(centres, radius)[1].sum(axis=(0, 1))

    def fit(
        self, centres: np.ndarray, radius: float, max_radius: float, max_nfev: int
    ) -> tuple[np.ndarray, float, float]:
        """Centres (S, 2) and the discs' common radius moved to the least χ²; (centres, radius, χ²).

        The radius is fitted because it moves the centres: the ball maps a disc onto the
        sensor unevenly, so a template of the wrong size puts its light's centre elsewhere
        (0.25 mm too large a radius drew sources 4 mm apart 30 µm closer together)."""
        from scipy.optimize import least_squares

        def residuals(x):
            return self.solve(x[:-1].reshape(-1, 2) * 1e-3, x[-1] * 1e-3)[0]

        # In millimetres, so that least_squares' relative step (0.01 of max(1, |x|)) is 10-40 µm:
        # a small fraction of a pixel on the sensor, large against the templates' rounding.
        start = np.append(np.asarray(centres, float).ravel() * 1e3, min(radius, max_radius) * 1e3)
        lower = np.full(start.size, -np.inf)
        upper = np.full(start.size, np.inf)
        lower[-1], upper[-1] = 0.02, max_radius * 1e3
        result = least_squares(
            residuals, start, bounds=(lower, upper), diff_step=0.01, xtol=2e-4, ftol=1e-5, max_nfev=max_nfev
        )
        # result.fun is the residual at result.x: χ² without solving there again.
        return result.x[:-1].reshape(-1, 2) * 1e-3, float(result.x[-1]) * 1e-3, float(result.fun @ result.fun)


def refine_layout(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    first: list[Source],
    seeds: list[tuple[float, float]] = (),
    *,
    min_gain: float = 0.02,
    min_share: float = 0.02,
    min_distance: float = 0.5e-3,
    max_radius: float = 1.5e-3,
    max_sources: int = 24,
    margin_px: int = 48,
    inset_px: int = 8,
    max_nfev: int = 40,
    screen_nfev: int = 4,
    screen_seeds: int = 2,
) -> LayoutFit:
    """Point sources moved to where their templates explain the data best, and added one
    at a time while each addition explains a share of what is left.

    The first guess (the candidate grid's local maxima) is resolution-limited: a source
    between grid points shares its light out with its neighbours, whose centroid pulls it
    towards the others, and a source whose light the grid gave to its neighbours has no
    local maximum at all. Here the sources' (u, v) are free and their intensities are
    solved for at every step (:class:`_LayoutProblem`), so positions come out to a small
    fraction of the grid's spacing. Then each seed (:func:`seeds_from_strength`) farther
    than ``min_distance`` from every source is tried as one more source; the best is kept,
    and every position refitted, if it lowers χ² by at least ``min_gain`` of its value and
    carries at least ``min_share`` of the brightest source's light; the search stops at
    the first seed that does not, or at ``max_sources``.

    A seed is judged after ``screen_nfev`` steps of the whole fit, not where it stands: the
    sources found so far may have widened their discs over a missed source's light (four
    guesses at 23.6 µm pixels grew to 1.3 mm for 0.5), and then one more source helps only
    once the discs shrink back. Where they stand, with the other sources and the radius
    held, the seeds' χ² then differ by 0.01-0.1 %: a poor ranking. So the ``screen_seeds``
    best there are screened in turn and the first that reaches ``min_gain`` is taken (on
    the demo's reduced rig, in its test, the best gained 1.2 %, the second 3.4 %).

    Parameters
    ----------
    data : list of LayoutData
        A few merged positions spread over the sweep.
    builder : TemplateBuilder
        The templates of the processing.
    cfa_pattern : str
        The mosaic's colour filter layout.
    first : list of Source
        The first guess.
    seeds : sequence of (u, v)
        Where to look for sources the first guess missed, strongest first.

    Returns
    -------
    LayoutFit
        Unrefined (``refined`` False, ``message`` why) when no position has a window where
        the first guess's templates are all whole.
    """
    if not first:
        return LayoutFit([], False, "no first guess to refine")
    from threadpoolctl import threadpool_limits

    # One BLAS thread, as in a Dask worker: the fit is iterative and amplifies a product summed in
    # another order (several threads) into the centres (~1e-11 m) and the rays drawn from them
    # (~3e-8 m). Its matrices are a few columns wide: one thread is no slower.
    with threadpool_limits(limits=1, user_api="blas"):
        problem = _LayoutProblem(data, builder, cfa_pattern, first, margin_px, inset_px)
        if not problem.windows or problem.pixels < 16:
            return LayoutFit(list(first), False, "no position has a window where every template is whole")
        radius = float(np.median([s.radius for s in first]))
        centres, radius, chi2 = problem.fit(np.array([s.centre for s in first], float), radius, max_radius, max_nfev)
        steps = [(len(centres), chi2)]
        # Two guesses of one source (the grid shares a source's light out) meet when fitted: the
        # fainter goes, and the rest are refitted.
        while len(centres) > 1:
            gap, i, j = _closest_pair(centres)
            if gap >= min_distance:
                break
            light = problem.light(centres, radius)
            centres = np.delete(centres, i if light[i] < light[j] else j, axis=0)
            centres, radius, chi2 = problem.fit(centres, radius, max_radius, max_nfev)
            steps.append((len(centres), chi2))
        untried = [np.array(seed, float) for seed in seeds]
        while len(centres) < max_sources:
            untried = [seed for seed in untried if np.min(np.hypot(*(centres - seed).T)) >= min_distance]
            if not untried:
                break
            trials = np.array([problem.chi2(np.vstack([centres, seed]), radius) for seed in untried])
            passed = False
            for k in np.argsort(trials)[:screen_seeds]:
                grown, grown_radius, grown_chi2 = problem.fit(
                    np.vstack([centres, untried[k]]), radius, max_radius, screen_nfev
                )
                if grown_chi2 <= (1.0 - min_gain) * chi2:
                    untried.pop(k)
                    passed = True
                    break
            if not passed:
                break
            grown, grown_radius, grown_chi2 = problem.fit(grown, grown_radius, max_radius, max_nfev)
            light = problem.light(grown, grown_radius)
            too_close = _closest_pair(grown)[0] < min_distance
            if grown_chi2 > (1.0 - min_gain) * chi2 or light[-1] < min_share * light.max() or too_close:
                break
            centres, radius, chi2 = grown, grown_radius, grown_chi2
            steps.append((len(centres), chi2))
        # A source left with no light (the unmixing gave it nothing anywhere) is not one.
        keep = problem.light(centres, radius) > 0
        if not np.all(keep) and np.any(keep):
            centres, radius, chi2 = problem.fit(centres[keep], radius, max_radius, max_nfev)
            steps.append((len(centres), chi2))
        sources = [Source(f"source-{k}", (float(u), float(v)), radius) for k, (u, v) in enumerate(centres)]
        count = f"{len(sources)} source{'s' * (len(sources) != 1)}"
        return LayoutFit(
            sources,
            True,
            f"{count} of radius {radius * 1e3:.2f} mm, χ² {chi2:.4g} over {problem.pixels} pixels",
            chi2,
            problem.pixels,
            steps,
        )


@dataclass(frozen=True)
class ApertureFit:
    """The camera's aperture diameter (the pinhole's) that the data favour, :func:`fit_aperture`.

    ``chi2`` and ``chi2_described`` are the weighted squared residual over ``pixels`` at the
    fitted and at the described diameter; ``evaluations`` counts the χ² computed."""

    diameter_m: float
    described_m: float
    chi2: float
    chi2_described: float
    pixels: int
    evaluations: int


def fit_aperture(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    layout: list[Source],
    *,
    bounds: tuple[float, float] = (0.75, 1.25),
    xatol: float = 1e-4,
    margin_px: int = 48,
    inset_px: int = 8,
) -> ApertureFit:
    """The aperture diameter whose templates, at the sources' known places, explain the data best.

    The aperture sets the point spread's size, and the unmixing is a deconvolution: a
    description 1 % off put the fits 4-5 % off the truth on the demo rig, 10 % off 42-48 %
    (``mirrorgonio bench tolerance``). The data tell it apart: χ² of the templates over the
    pixels of :class:`_LayoutProblem` (their intensities solved for by NNLS) rose from 1.066
    to 1.09-1.13 a pixel over 72 845 pixels with the diameter 1 % off. So the diameter is
    the minimum of that χ² over ``bounds`` × the described one (bounded Brent search,
    ``scipy.optimize.minimize_scalar``, to ``xatol`` of the described diameter). The pixels
    stay those where the narrowest aperture tried gives whole templates, so that every trial
    is judged on the same pixels.

    Parameters
    ----------
    data : list of LayoutData
        A few merged positions spread over the sweep.
    builder : TemplateBuilder
        The templates as the rig is described.
    cfa_pattern : str
        The mosaic's colour filter layout.
    layout : list of Source
        The sources, known (their centres and radii are held).

    Raises
    ------
    SourcesError
        No position with a window where every template is whole, or the best diameter at a
        bound of the search (the description is further off than ``bounds``, or the
        templates cannot explain the data).
    """
    from dataclasses import replace

    if not layout:
        raise SourcesError("no sources to fit the aperture at")
    described = builder.geometry.aperture_radius
    narrowest = replace(builder, geometry=replace(builder.geometry, aperture_radius=described * bounds[0]))
    centres = np.array([s.centre for s in layout], float)
    radii = np.array([s.radius for s in layout], float)

    def chi2_at(problem: _LayoutProblem, scale: float) -> float:
        problem.set_aperture(described * scale)
        return problem.chi2(centres, radii)

    scale, chi2, chi2_described, pixels, evaluations = _fit_scale(
        data,
        narrowest,
        cfa_pattern,
        layout,
        margin_px,
        inset_px,
        bounds,
        xatol,
        chi2_at,
        "aperture",
        lambda x: f"{2e3 * described * x:.4g} mm",
    )
    return ApertureFit(2.0 * described * scale, 2.0 * described, chi2, chi2_described, pixels, evaluations)


def _fit_scale(data, builder, cfa_pattern, layout, margin_px, inset_px, bounds, xatol, chi2_at, what: str, shown):
    """The factor in ``bounds`` on one of the camera's described numbers whose templates explain
    the data best (bounded Brent search, ``scipy.optimize.minimize_scalar``, to ``xatol``):
    (factor, χ² there, χ² at 1, pixels, evaluations). ``chi2_at(problem, factor)`` sets the
    trial on the :class:`_LayoutProblem` (its pixels fixed by ``builder``) and returns χ²;
    ``shown(factor)`` is the number as an error names it. A best factor at a bound is an error."""
    from scipy.optimize import minimize_scalar
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):  # as in refine_layout: one order of sums
        problem = _LayoutProblem(data, builder, cfa_pattern, list(layout), margin_px, inset_px)
        if not problem.windows or problem.pixels < 16:
            raise SourcesError("no position has a window where every template is whole")
        evaluations = 0

        def chi2(factor: float) -> float:
            nonlocal evaluations
            evaluations += 1
            return chi2_at(problem, factor)

        best = minimize_scalar(chi2, bounds=bounds, method="bounded", options={"xatol": xatol})
        at_described = chi2(1.0)
    factor = float(best.x)
    if min(factor - bounds[0], bounds[1] - factor) <= 2 * xatol:
        raise SourcesError(
            f"the best {what} lies at the search's bound ({shown(factor)}, {100 * (factor - 1):+.1f} % "
            f"of the described {shown(1.0)})"
        )
    return factor, float(best.fun), at_described, problem.pixels, evaluations


@dataclass(frozen=True)
class SensorDistanceFit:
    """:func:`fit_sensor_distance`'s result: the distance, and χ² there and at the described one."""

    sensor_distance_m: float
    described_m: float
    chi2: float
    chi2_described: float
    pixels: int
    evaluations: int
    sources_refitted: bool


def fit_sensor_distance(
    data: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    layout: list[Source],
    *,
    refit: bool = True,
    bounds: tuple[float, float] = (0.98, 1.02),
    xatol: float = 2e-4,
    max_radius: float = 1.5e-3,
    max_nfev: int = 40,
    margin_px: int = 48,
    inset_px: int = 8,
) -> SensorDistanceFit:
    """The sensor distance (pinhole to sensor) whose templates explain the data best.

    It sets the image's scale: 0.5 % too long made the search for the sources on the demo rig
    add four that are not there (fits 38 % off), and χ² with those nine did not give it away
    (``mirrorgonio bench tolerance``). Held at the sources such a search found, χ² is least
    near the wrong distance too: the spurious sources lock it. So with ``refit`` (sources found
    in the data) the sources' centres and common radius are fitted again at every trial
    distance (:meth:`_LayoutProblem.fit`, as many sources as ``layout`` has) and the distance
    is the one whose best layout explains the data best: on the demo rig described 0.5 %
    long, seven sources found, χ²/pixel 1.185 as described and 1.060-1.061 at 0.994-0.995 of it
    (the truth: 0.99502). Without ``refit`` (sources whose places are known) they are held.
    A bounded Brent search (``scipy.optimize.minimize_scalar``) over ``bounds`` × the described
    distance, to ``xatol`` of it; the pixels are those of the described geometry's windows.

    Raises
    ------
    SourcesError
        No sources, no position with a window where every template is whole, or the best
        distance at a bound of the search.
    """
    if not layout:
        raise SourcesError("no sources to fit the sensor distance at")
    described = builder.geometry.sensor_distance
    centres = np.array([s.centre for s in layout], float)
    radii = np.array([s.radius for s in layout], float)

    def chi2_at(problem: _LayoutProblem, scale: float) -> float:
        problem.set_geometry(builder.geometry.with_sensor_distance(described * scale))
        if refit:
            return problem.fit(centres, float(np.median(radii)), max_radius, max_nfev)[2]
        return problem.chi2(centres, radii)

    scale, chi2, chi2_described, pixels, evaluations = _fit_scale(
        data,
        builder,
        cfa_pattern,
        layout,
        margin_px,
        inset_px,
        bounds,
        xatol,
        chi2_at,
        "sensor distance",
        lambda x: f"{1e3 * described * x:.3f} mm",
    )
    return SensorDistanceFit(described * scale, described, chi2, chi2_described, pixels, evaluations, refit)


def _closest_pair(centres: np.ndarray) -> tuple[float, int, int]:
    """(distance, i, j) of the two closest of ``centres`` (at least two)."""
    return min((math.dist(centres[i], centres[j]), i, j) for i in range(len(centres)) for j in range(i))

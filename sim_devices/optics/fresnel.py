"""The pinhole's point spread from scalar Fresnel diffraction, over each channel's spectral band.

A point whose (virtual) image lies in front of the pinhole sends a spherical (or, after a curved
mirror, astigmatic) wave onto the aperture. In the paraxial (Fresnel) approximation the field at
the sensor is (Goodman, *Introduction to Fourier Optics*, 3rd ed., §4.2, eq. 4-17, with the
incident wave's quadratic phase of §5.1)::

    U(x) ∝ ∫ A(ρ) exp(iπ |ρ|² (1/z₁ + 1/z₂) / λ) exp(−2πi x·ρ / (λ z₂)) d²ρ

with ``A`` the aperture's transmission, ``z₁`` the distance of the point's image in front of the
pinhole and ``z₂`` the sensor's behind it; the intensity is ``|U|²``. Its one number is the Fresnel
number ``N_F = a²/λ · (1/z₁ + 1/z₂)`` of a hole of radius ``a``: ``N_F ≫ 1`` gives the aperture's
geometric shadow, ``N_F ≪ 1`` the Fraunhofer (Airy) pattern, and on the axis of a circular hole
``|U(0)|² ∝ sin²(π N_F / 2)`` (Born & Wolf, *Principles of Optics*, 7th ed., §8.8.1, the Lommel
functions at ``v = 0``), four times the shadow's level when ``N_F`` is odd.

Here the phase is written about the chief ray with the exact second derivatives of the optical
path ``L(ρ, p)`` from the point through the aperture point ``ρ`` to the sensor point ``p``
(pixels), which holds off the axis and through an astigmatic mirror too::

    U(p) ∝ ∫ A(ρ) exp(iπ ρᵀQρ / λ) exp(2πi ρᵀG p / λ) d²ρ,   Q = ∂²L/∂ρ²,  G = −∂²L/∂ρ∂p

(:class:`PathCurvature`). On the axis ``Q = (1/z₁ + 1/z₂) I`` and ``G = (pitch / z₂) I``. Fermat's
principle ties the two to the rays: a ray through ``ρ`` lands at ``p = −G⁻¹Qρ``, so ``Q = −G M``
with ``M`` the rays' magnification (pixels per metre of aperture), which the renderer measures by
tracing neighbouring rays; the phase's stationary point is then the geometric shadow exactly.

Numerically (:func:`fresnel_intensity`): the aperture is sampled in the coordinates ``σ = Gᵀρ``,
where the integral is an inverse Fourier transform onto the pixel grid, fine enough for the edge
(``edge_samples`` cells across the hole, its transmission the cells' area fraction) and for the
quadratic phase (at most π/4 a cell at the edge), and padded so the sensor-plane sampling (the
pixel pitch over an odd ``oversample``) is at least 2.5 times the intensity's band limit ``2σ_max/λ``
(the aperture's autocorrelation: Goodman §6.3). The intensity is normalised to unit flux, the
hole's area by Parseval's theorem, every tail gathered into the transform's period, and
integrated over each pixel's area exactly, as the band-limited function's Fourier series times
``sinc(f_x) sinc(f_y)``.

The band (:func:`channel_band`): a channel's Gaussian sensitivity of FWHM
``channel_bandwidths_m`` about ``channel_wavelengths_m`` is integrated with Gauss–Hermite
quadrature (Abramowitz & Stegun 25.4.46), exact for a point spread polynomial in λ to degree
``2n − 1``; a tabulated ``spectral_response`` with the trapezoidal rule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import fft as sfft

from drivers.contracts.rig import Camera
from sim_devices.optics.aperture import ApertureShape

#: Wavelengths a band is integrated over by default (Gauss–Hermite nodes): the reference rig's
#: point spreads differ from 15 nodes' by less than 2e-4 of their peak (measured 7e-5) and
#: their FWHM by less than 0.01 px (measured 0.001; tests/test_fresnel.py).
BAND_SAMPLES = 7
#: Aperture cells across the hole's diameter, by default.
EDGE_SAMPLES = 128
#: The sensor-plane sampling against the intensity's band limit (≥ 2 is Nyquist).
BAND_LIMIT_MARGIN = 2.5


# --- the optical path about the chief ray ----------------------------------------------------
@dataclass(frozen=True)
class PathCurvature:
    """The optical path's second derivatives about a point's chief ray.

    Attributes
    ----------
    quadratic : ndarray, shape (2, 2)
        ``Q = ∂²L/∂ρ²`` (1/m): the incident wave's curvature plus the sensor side's, in the
        aperture plane (x along the image's columns, y along its rows, seen from the sensor).
    conjugate : ndarray, shape (2, 2)
        ``G = −∂²L/∂ρ∂p`` (1/pixel): how the sensor point ``p`` (pixels) tilts the phase across the
        aperture; ``(pitch/r)(I − ûûᵀ)`` for a sensor point at distance ``r`` along ``û``.
    pitch : float
        The pixel pitch (m); ``G / pitch`` is the sensor side's share of ``Q``.
    """

    quadratic: np.ndarray
    conjugate: np.ndarray
    pitch: float

    @classmethod
    def on_axis(
        cls,
        image_distance: float | tuple[float, float],
        sensor_distance: float,
        pitch: float,
        angle: float = 0.0,
    ) -> PathCurvature:
        """A point on the axis: its image ``image_distance`` in front of the pinhole (two values:
        astigmatic, along axes turned by ``angle`` radians from x), the sensor behind it."""
        z1 = np.broadcast_to(np.asarray(image_distance, dtype=float), (2,))
        c, s = math.cos(angle), math.sin(angle)
        rot = np.array([[c, -s], [s, c]])
        curvature = rot @ np.diag(1.0 / z1) @ rot.T
        return cls(curvature + np.eye(2) / sensor_distance, np.eye(2) * pitch / sensor_distance, pitch)

    @classmethod
    def from_rays(
        cls, magnification: np.ndarray, sensor_point: tuple[float, float], sensor_distance: float, pitch: float
    ) -> PathCurvature:
        """From the rays' magnification ``M = ∂p/∂ρ`` (pixels per metre of aperture) about a
        chief ray that meets the sensor ``sensor_point`` (metres from the principal point, along
        the image's columns and rows): ``Q = −G M``, symmetrised (it is a Hessian)."""
        u = np.asarray(sensor_point, dtype=float)
        r = math.sqrt(float(u @ u) + sensor_distance**2)
        u = u / r
        conjugate = pitch / r * (np.eye(2) - np.outer(u, u))
        q = -conjugate @ np.asarray(magnification, dtype=float)
        return cls(0.5 * (q + q.T), conjugate, pitch)

    def image_distances(self) -> tuple[float, float, float]:
        """The point's image distances in front of the pinhole along the incident wave's principal
        axes, and the first axis's angle (radians from x).

        The wave's share of ``Q`` is ``C = Q − G/pitch``; a wave of curvature ``K`` (in the plane
        across the chief ray) arriving along ``û`` gives ``C = S^½ K S^½`` with
        ``S = (I − ûûᵀ) = G r / pitch``, ``r = pitch / (G's largest eigenvalue)``.
        """
        r = self.pitch / float(np.linalg.eigvalsh(self.conjugate)[-1])
        values, vectors = np.linalg.eigh(self.conjugate * (r / self.pitch))
        root_inv = vectors @ np.diag(values**-0.5) @ vectors.T
        curvature = root_inv @ (self.quadratic - self.conjugate / self.pitch) @ root_inv
        values, vectors = np.linalg.eigh(curvature)
        return 1.0 / values[0], 1.0 / values[1], math.atan2(vectors[1, 0], vectors[0, 0])

    def fresnel_number(self, radius: float, wavelength: float) -> float:
        """``a² / λ · (1/z₁ + 1/z₂)``, with ``Q``'s mean curvature for ``(1/z₁ + 1/z₂)``."""
        return radius**2 * float(np.trace(self.quadratic)) / 2.0 / wavelength

    def magnification(self) -> np.ndarray:
        """The rays' magnification ``M = −G⁻¹Q`` (pixels per metre of aperture)."""
        return -np.linalg.solve(self.conjugate, self.quadratic)

    def quantised(self, quadratic_step: float, conjugate_step: float) -> PathCurvature:
        """Rounded to multiples of the steps (a cache key's path; see :attr:`key`)."""
        q = np.round(self.quadratic / quadratic_step) * quadratic_step
        g = np.round(self.conjugate / conjugate_step) * conjugate_step
        return PathCurvature(0.5 * (q + q.T), 0.5 * (g + g.T), self.pitch)

    @property
    def key(self) -> tuple[float, ...]:
        return tuple(np.round(np.concatenate([self.quadratic.ravel(), self.conjugate.ravel()]), 12).tolist())


# --- the spectral band ----------------------------------------------------------------------------
def channel_band(camera: Camera, channel: int, samples: int = BAND_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths (m) and weights (summing to 1) that integrate over channel 0, 1 or 2's band.

    The camera's ``spectral_response`` when it has one (``samples`` equally spaced wavelengths
    over the curve's support, trapezoidal weights times the response), else a Gaussian of FWHM
    ``channel_bandwidths_m`` about ``channel_wavelengths_m`` by Gauss–Hermite quadrature; a
    zero bandwidth is the one wavelength.
    """
    if camera.spectral_response is not None:
        grid, response = camera.spectral_response.curve(channel)
        lit = np.flatnonzero(response > 0)
        lo, hi = grid[max(lit[0] - 1, 0)], grid[min(lit[-1] + 1, grid.size - 1)]
        wavelengths = np.linspace(lo, hi, max(samples, 2))
        weights = np.interp(wavelengths, grid, response) * np.gradient(wavelengths)
        weights[[0, -1]] *= 0.5
        keep = weights > 0
        return wavelengths[keep], weights[keep] / weights[keep].sum()
    centre = camera.channel_wavelengths_m[channel]
    fwhm = camera.channel_bandwidths_m[channel]
    if fwhm == 0 or samples == 1:
        return np.array([centre]), np.array([1.0])
    sigma = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    nodes, weights = np.polynomial.hermite.hermgauss(samples)
    return centre + math.sqrt(2.0) * sigma * nodes, weights / math.sqrt(math.pi)


# --- the sampling -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class PsfGrid:
    """The transform's size ``n`` (samples a side) and the sensor-plane samples per pixel
    ``oversample`` (odd); the point spread's period is ``n / oversample`` pixels."""

    n: int
    oversample: int

    @property
    def pixels(self) -> int:
        return self.n // self.oversample


def psf_grid(
    aperture: ApertureShape,
    wavelengths: np.ndarray,
    path: PathCurvature,
    *,
    edge_samples: int = EDGE_SAMPLES,
    oversample: int | None = None,
    min_pixels: int = 0,
) -> PsfGrid:
    """The smallest transform that resolves the aperture's edge and phase for every wavelength,
    samples the sensor plane finely enough, and holds the pattern (see the module's docstring)."""
    g_sv = np.linalg.svd(path.conjugate, compute_uv=False)
    radius = aperture.radius
    sigma_max = g_sv[0] * radius
    lam_min, lam_max = float(np.min(wavelengths)), float(np.max(wavelengths))
    band_limit = 2.0 * sigma_max / lam_min  # cycles per pixel
    if oversample is None:
        oversample = 1 + 2 * max(0, math.ceil((BAND_LIMIT_MARGIN * band_limit - 1.0) / 2.0))
    s = oversample
    cell = min(2.0 * radius / edge_samples, aperture.finest_detail / 3.0)
    n_edge = s * lam_max / (g_sv[1] * cell)  # dσ = sλ/n, a cell of dσ/g in the aperture plane
    q_sigma = np.linalg.solve(path.conjugate, np.linalg.solve(path.conjugate, path.quadratic).T)
    n_phase = 8.0 * s * np.linalg.norm(q_sigma, 2) * sigma_max
    shadow = np.linalg.norm(path.magnification(), 2) * radius  # pixels
    ring = lam_max / (2.0 * g_sv[1] * radius)  # pixels
    n_window = s * max(4.0 * (shadow + 24.0 * ring), min_pixels)
    n = int(math.ceil(max(n_edge, n_phase, n_window, 64.0)))
    n = sfft.next_fast_len(n)
    while n % (2 * s):
        n = sfft.next_fast_len(n + 1)
    return PsfGrid(n, s)


# --- the point spread ---------------------------------------------------------------------------------
def fresnel_intensity(aperture: ApertureShape, wavelength: float, path: PathCurvature, grid: PsfGrid) -> np.ndarray:
    """The Fresnel intensity at one wavelength on the sensor-plane grid (``grid.n`` samples a
    side, ``1/grid.oversample`` pixel apart, the chief ray's point at ``[n//2, n//2]``),
    normalised to unit flux (each sample the fraction of the flux in its cell)."""
    n, s = grid.n, grid.oversample
    d_sigma = s * wavelength / n  # metres per pixel: σ·p/λ = j k / n
    g_inv_t = np.linalg.inv(path.conjugate).T
    sigma_max = np.linalg.norm(path.conjugate.T, 2) * aperture.radius
    half = int(math.ceil(sigma_max / d_sigma)) + 2
    if 2 * half + 1 > n:
        raise ValueError("the transform is smaller than the aperture: increase the grid")
    j = np.arange(-half, half + 1)
    sx, sy = np.meshgrid(j * d_sigma, j * d_sigma)  # x along columns, y along rows
    ax = g_inv_t[0, 0] * sx + g_inv_t[0, 1] * sy
    ay = g_inv_t[1, 0] * sx + g_inv_t[1, 1] * sy
    cell = d_sigma * math.sqrt(abs(float(np.linalg.det(g_inv_t))))
    q = path.quadratic
    phase = (math.pi / wavelength) * (q[0, 0] * ax * ax + 2.0 * q[0, 1] * ax * ay + q[1, 1] * ay * ay)
    transmission = aperture.transmission(ax, ay, cell)
    pupil = transmission * np.exp(1j * phase)
    # U(k) = Σ_j P(j) exp(+2πi j·k / n): the inverse DFT, the pupil's rows first (only those
    # that hold the aperture), then every column.
    index = j % n
    rows = np.zeros((j.size, n), dtype=complex)
    rows[:, index] = pupil
    rows = sfft.ifft(rows, axis=1, workers=-1)
    field = np.zeros((n, n), dtype=complex)
    field[index, :] = rows
    field = sfft.ifft(field, axis=0, workers=-1, overwrite_x=True)
    # The flux is the hole's area, Σ T (Parseval, with T the cells' area fractions). The grey
    # edge cells carry only Σ T² < Σ T: what they miss is the sharp edge's scatter to angles
    # beyond the grid's period, which a period gathers back as a uniform floor (1/n² of it a
    # sample, ~1e-9 of the peak): adding it keeps the flux exact and the core unbiased.
    intensity = sfft.fftshift(field.real**2 + field.imag**2) * (n * n / transmission.sum())
    intensity += (1.0 - intensity.sum()) / (n * n)
    return intensity


def to_pixels(fine: np.ndarray, grid: PsfGrid, *, pixel_integrated: bool = True) -> np.ndarray:
    """A fine-grid intensity (:func:`fresnel_intensity`, or a band's weighted sum of them) on the
    pixel grid: each pixel's fraction of the flux, integrated over its area (exact for the
    band-limited intensity: its Fourier series times ``sinc(f_x) sinc(f_y)``, f in cycles per
    pixel), or the intensity at the pixel's centre times a pixel's area (``pixel_integrated``
    False). The chief ray's point is at ``[m//2, m//2]``, ``m = grid.pixels``."""
    s = grid.oversample
    density = fine * s * s  # flux per pixel area
    if pixel_integrated:
        spectrum = sfft.rfft2(sfft.ifftshift(density), workers=-1)
        fy = sfft.fftfreq(grid.n, d=1.0 / s)[:, None]
        fx = sfft.rfftfreq(grid.n, d=1.0 / s)[None, :]
        spectrum *= np.sinc(fy) * np.sinc(fx)
        density = sfft.fftshift(sfft.irfft2(spectrum, s=(grid.n, grid.n), workers=-1))
    return np.ascontiguousarray(density[::s, ::s])


def fresnel_psf(
    aperture: ApertureShape,
    wavelengths: float | np.ndarray,
    path: PathCurvature,
    *,
    weights: np.ndarray | None = None,
    pixel_integrated: bool = True,
    edge_samples: int = EDGE_SAMPLES,
    oversample: int | None = None,
    min_pixels: int = 0,
) -> np.ndarray:
    """The point spread on the pixel grid: the Fresnel intensity of a point (``path``) through
    ``aperture``, averaged over ``wavelengths`` with ``weights`` (equal by default; each
    wavelength's pattern has unit flux), per pixel (see :func:`to_pixels`).

    Returns
    -------
    ndarray, shape (m, m)
        The fraction of the point's flux in each pixel, the chief ray's point at the centre
        pixel ``[m//2, m//2]``; ``m`` is the pattern's period in pixels (at least ``min_pixels``),
        and the array sums to 1.
    """
    lams = np.atleast_1d(np.asarray(wavelengths, dtype=float))
    w = np.full(lams.size, 1.0 / lams.size) if weights is None else np.asarray(weights, dtype=float) / np.sum(weights)
    grid = psf_grid(aperture, lams, path, edge_samples=edge_samples, oversample=oversample, min_pixels=min_pixels)
    fine = np.zeros((grid.n, grid.n))
    for lam, weight in zip(lams, w, strict=True):
        fine += weight * fresnel_intensity(aperture, float(lam), path, grid)
    return to_pixels(fine, grid, pixel_integrated=pixel_integrated)


def channel_psf(
    camera: Camera,
    aperture: ApertureShape,
    channel: int,
    path: PathCurvature,
    samples: int = BAND_SAMPLES,
    **options: Any,
) -> np.ndarray:
    """:func:`fresnel_psf` over channel 0, 1 or 2's band (:func:`channel_band`)."""
    wavelengths, weights = channel_band(camera, channel, samples)
    return fresnel_psf(aperture, wavelengths, path, weights=weights, **options)

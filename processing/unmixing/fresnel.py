"""The pinhole's point spread in the Fresnel regime, for the templates.

A point of the light plane is seen through the ball as a virtual point in front of the pinhole;
the spherical wave from it passes the aperture and draws on the sensor, ``z2`` behind it, the
scalar Fresnel pattern (Goodman, *Introduction to Fourier Optics*, 3rd ed., §4.2, eq. 4-17)

    U(s) ∝ ∫ A(ρ) exp(iπ ρᵀQρ / λ) exp(−2πi s·ρ / (λ z2)) d²ρ,

``A`` the aperture's transmission, ``s`` the place on the sensor from where the chief ray lands.
``Q`` is the curvature of the phase across the aperture: ``(1/z1 + 1/z2)·I`` for a point ``z1``
in front, a symmetric matrix where the ball's curvature makes the wave astigmatic. Where the
phase varies fast (Fresnel number ``a²/λ·(1/z1 + 1/z2)`` ≫ 1) the stationary points give back
the geometric shadow: the aperture point ``ρ`` lights ``s = z2·Q·ρ``. So ``Q`` is read off the
template's own geometry, the affine map from the aperture's rim to its shadow's outline on the
sensor, which the templates trace through the mirror: ``Q = M / z2``.

The integral is a matrix Fourier transform of the sampled aperture field (Soummer et al. 2007,
"Fast computation of Lyot-style coronagraph propagation", Optics Express 15, 15935): two
matrix products onto exactly the pixel grid wanted, with no padding or resampling. Each
channel's pattern is the mean over its spectral band (the camera's Gaussian bands, or its
tabulated response), normalised so that the whole sensor plane receives unit flux (Parseval).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from drivers.contracts.rig import Camera

#: Samples across the aperture's larger diameter: the phase across it is a few radians and the
#: edge is anti-aliased, so 96 resolve both (the pattern moves by < 1e-4 of its peak at 192).
APERTURE_SAMPLES = 96

#: Pixels beyond the kernel's reach on which the pattern is sampled, so that each pixel's mean
#: (the box's transfer function, applied on a periodic grid) takes nothing from the other side.
#: The box's weights fall as 1/k²: the pattern's values 16 px out come back at under 4e-4 of them.
BOX_MARGIN = 16

#: Wavelengths a channel's band is sampled at (a Gaussian band over ±2.5σ).
BAND_SAMPLES = 9


@dataclass(frozen=True)
class PupilShape:
    """The aperture: an ellipse of full diameters ``axes_m`` (its own x, then y), its x axis
    ``angle_rad`` from the camera's x axis towards its y axis. A circle has equal axes."""

    axes_m: tuple[float, float]
    angle_rad: float = 0.0

    @property
    def area(self) -> float:
        return math.pi * self.axes_m[0] * self.axes_m[1] / 4.0

    def transmission(self, x: np.ndarray, y: np.ndarray, step: float) -> np.ndarray:
        """The fraction of each ``step``-wide cell about (x, y) inside the ellipse: 1 − the
        cell's centre's signed distance to the edge over ``step``, plus ½, clipped to [0, 1]
        (the share of a cell cut by a straight edge along its side).

        It is continuous in the axes and the angle, so that a fit which moves them by a
        hundredth of a per cent sees the pattern move smoothly: counted sub-samples jump as the
        edge crosses them, a noise that swamps such a step's change.
        """
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        a, b = 0.5 * self.axes_m[0], 0.5 * self.axes_m[1]
        u, v = c * x + s * y, -s * x + c * y
        rho = np.hypot(u / a, v / b)
        # ρ − 1 over |∇ρ|: the distance to the edge to first order (exact on the axes).
        gradient = np.hypot(u / (a * a), v / (b * b)) / np.maximum(rho, 1e-12)
        distance = (rho - 1.0) / np.maximum(gradient, 1e-12 / max(a, b))
        return np.clip(0.5 - distance / step, 0.0, 1.0)


Band = tuple[tuple[float, ...], tuple[float, ...]]


@dataclass(frozen=True)
class FresnelPupil:
    """Each channel's band as (wavelengths, weights), for the Fresnel templates; the aperture's
    size and shape are the geometry's (``RigGeometry.aperture_radius``, ``aperture_shape``), which
    the rig's fit corrects. Hashable: the templates' kernels are cached on it."""

    bands: tuple[Band, Band, Band]

    @staticmethod
    def shape(aperture_radius: float, aperture_shape: tuple[float, float, float]) -> PupilShape:
        """The aperture: the circle of ``aperture_radius`` deformed by the symmetric matrix
        ``aperture_shape`` (xx, xy, yy), its eigenvalues the axes' ratios.

        Examples
        --------
        >>> shape = FresnelPupil.shape(1e-4, (1.0, 0.025, 1.0))  # 5 % elliptical, along the diagonal
        >>> [round(axis * 1e6, 2) for axis in shape.axes_m], round(math.degrees(shape.angle_rad), 1)
        ([205.0, 195.0], 45.0)
        """
        xx, xy, yy = aperture_shape
        values, vectors = np.linalg.eigh(np.array([[xx, xy], [xy, yy]]))
        angle = math.atan2(vectors[1, 1], vectors[0, 1])  # the larger axis's direction
        diameter = 2.0 * aperture_radius
        return PupilShape((diameter * float(values[1]), diameter * float(values[0])), angle)

    @classmethod
    def from_camera(cls, camera: Camera) -> FresnelPupil:
        """The rig camera's bands (``channel_bandwidths_m`` about ``channel_wavelengths_m``, or
        ``spectral_response``)."""
        if camera.spectral_response is not None:
            bands = tuple(tabulated_band(*camera.spectral_response.curve(c)) for c in range(3))
        else:
            bands = tuple(
                band_samples(centre, width)
                for centre, width in zip(camera.channel_wavelengths_m, camera.channel_bandwidths_m, strict=True)
            )
        return cls(bands)  # type: ignore[arg-type]


def tabulated_band(wavelengths: np.ndarray, response: np.ndarray, samples: int = 15) -> Band:
    """A tabulated channel response as :data:`BAND_SAMPLES`-like (wavelengths, weights):
    ``samples`` wavelengths evenly over where it responds, weighted by the response there."""
    responds = np.flatnonzero(response > 0)
    low = wavelengths[max(0, responds[0] - 1)]
    high = wavelengths[min(len(wavelengths) - 1, responds[-1] + 1)]
    grid = np.linspace(low, high, samples)
    weights = np.interp(grid, wavelengths, response, left=0.0, right=0.0)
    keep = weights > 0
    weights = weights[keep] / weights[keep].sum()
    return tuple(float(w) for w in grid[keep]), tuple(float(w) for w in weights)


def band_samples(centre: float, fwhm: float) -> Band:
    """Wavelengths and weights (summing to 1) over a Gaussian band of ``fwhm`` about ``centre``:
    :data:`BAND_SAMPLES` points evenly over ±2.5σ (one wavelength where ``fwhm`` is 0).

    Examples
    --------
    >>> waves, weights = band_samples(540e-9, 80e-9)
    >>> len(waves), round(sum(weights), 12), round(float(np.dot(waves, weights)) * 1e9, 6)
    (9, 1.0, 540.0)
    """
    if fwhm <= 0:
        return (centre,), (1.0,)
    sigma = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    x = np.linspace(-2.5, 2.5, BAND_SAMPLES)
    weights = np.exp(-0.5 * x**2)
    weights /= weights.sum()
    return tuple(float(centre + sigma * v) for v in x), tuple(float(w) for w in weights)


def fresnel_kernel(
    pupil: PupilShape,
    curvature: tuple[float, float, float],
    sensor_distance: float,
    pitch: float,
    band: Band,
    reach: int,
) -> np.ndarray:
    """The point spread on the pixel grid, offsets ``-reach..reach`` (rows, columns), as the
    fraction of the flux through the aperture each pixel's area receives (the pattern's mean
    over the pixel, times its area).

    A pixel integrates the pattern over its area; its centre's value alone is up to 1.7 % of the
    peak off that (the demo rig's 11.8 µm pixels, blue band; 0.4 % at 5.9 µm). The irradiance
    is band-limited: it is the Fourier transform of the aperture field's autocorrelation, which
    holds no separation beyond the aperture's diameter ``D``, so no frequency above
    ``D/(λ z2)`` (17 cycles/mm on the reference rig, a tenth of the 5.9 µm pixels' Nyquist).
    Sampled at the pixels' centres it is then whole, and its mean over each pixel is the
    product with the box's transfer function ``sinc(f_x p) sinc(f_y p)`` (on a grid
    :data:`BOX_MARGIN` px wider, cut back after). Against the mean over 9 × 9 points of each
    pixel it is within 5e-5 of the peak at 5.9 µm and 2e-4 at 11.8 µm (3 × 3 points: 4e-4 and
    1.7e-3), for a ninth of the matrix products.

    ``curvature`` is ``Q`` (1/m): its xx, xy and yy elements, in the camera's frame, where
    the sensor's columns and rows run against the camera's x and y (a half turn, which
    leaves the pattern of a centred ellipse unchanged). Cached: a run's templates share a few
    curvatures once rounded (:func:`rounded_curvature`).

    Examples
    --------
    On the axis of a circular hole of radius ``a`` the irradiance is ``4 sin²(π N_F / 2)`` times
    the incident wave's, ``N_F = a²/λ · (1/z1 + 1/z2)`` (Born & Wolf, *Principles of Optics*,
    §8.8.4): the reference pinhole at 540 nm, ``N_F`` = 0.84. The middle pixel's mean over its
    area lies 0.4 % under that peak.

    >>> a, z1, z2, pitch, wavelength = 1e-4, 0.186, 0.025, 5.9e-6, 540e-9
    >>> q = 1 / z1 + 1 / z2
    >>> kernel = fresnel_kernel(PupilShape((2 * a, 2 * a)), (q, 0.0, q), z2, pitch, ((wavelength,), (1.0,)), 40)
    >>> analytic = 4 * math.sin(math.pi * a * a * q / wavelength / 2) ** 2 * (z1 / (z1 + z2)) ** 2
    >>> round(float(kernel[40, 40] / (pitch**2 / (math.pi * a * a)) / analytic), 3)
    0.996
    """
    # The cached array itself, read-only: the templates keep its transform while it lives.
    return _kernel(pupil, tuple(float(c) for c in curvature), sensor_distance, pitch, band, reach)


@functools.lru_cache(maxsize=384)
def _kernel(
    pupil: PupilShape,
    curvature: tuple[float, float, float],
    sensor_distance: float,
    pitch: float,
    band: Band,
    reach: int,
) -> np.ndarray:
    qxx, qxy, qyy = curvature
    half = 0.5 * max(pupil.axes_m) * 1.02
    step = 2.0 * half / APERTURE_SAMPLES
    rho = -half + (np.arange(APERTURE_SAMPLES) + 0.5) * step
    x, y = np.meshgrid(rho, rho)
    transmission = pupil.transmission(x, y, step)
    quadratic = qxx * x * x + 2.0 * qxy * x * y + qyy * y * y
    # The pixels' centres (m) on the sensor, in the camera's frame, out to the box's margin.
    wide = reach + BOX_MARGIN
    s = -pitch * np.arange(-wide, wide + 1, dtype=float)
    irradiance = np.zeros((s.size, s.size))
    for wavelength, weight in zip(*band, strict=True):
        field = transmission * np.exp(1j * math.pi * quadratic / wavelength)
        # exp(−2πi s·ρ/(λ z2)), separable: U = E · field · Eᵀ (rows y, columns x).
        transform = np.exp(-2j * math.pi * np.outer(s, rho) / (wavelength * sensor_distance))
        u = transform @ field @ transform.T
        # |U|² d⁴ρ / (λ z2)² is the irradiance for unit incident amplitude.
        irradiance += weight * np.abs(u) ** 2 * step**4 / (wavelength * sensor_distance) ** 2
    rows, cols = np.fft.fftfreq(s.size), np.fft.rfftfreq(s.size)  # cycles per pixel
    box = np.sinc(rows)[:, None] * np.sinc(cols)[None, :]
    per_pixel = np.fft.irfft2(np.fft.rfft2(irradiance) * box, s=irradiance.shape)
    n = 2 * reach + 1
    # A pixel receives its mean irradiance times its area; the flux through the hole is its area
    # (the cells' transmission stands for the share of each cell inside: Σ A² would undercount the edge's cells).
    total = per_pixel[BOX_MARGIN : BOX_MARGIN + n, BOX_MARGIN : BOX_MARGIN + n] * pitch**2
    total /= np.sum(transmission) * step**2
    total.flags.writeable = False
    return total


def rounded_curvature(q: np.ndarray) -> tuple[float, float, float]:
    """``Q`` (2 × 2, made symmetric) as the cache's key: each element rounded to 5 units of the
    decade below a thousandth of the largest (0.05 /m on the rigs shipped, ``Q`` ≈ 45 /m).

    Half that step moves the pattern by at most 6e-4 of its peak (measured on the demo rig's
    red band), under the 1e-3 to which the kernel agrees with the simulator's, and a whole
    run's templates then share a few kernels (3 on the demo rig's 66 positions, against 28 at
    0.01 /m): each costs 27 matrix Fourier transforms (three bands of nine wavelengths).

    Examples
    --------
    >>> rounded_curvature(np.array([[45.3712, 0.0116], [0.0116, 45.3399]]))
    (45.35, 0.0, 45.35)
    """
    sym = 0.5 * (q + q.T)
    scale = 5.0 * 10.0 ** math.floor(math.log10(1e-3 * float(np.max(np.abs(sym)))))
    return (
        float(round(round(sym[0, 0] / scale) * scale, 12)),
        float(round(round(sym[0, 1] / scale) * scale, 12)),
        float(round(round(sym[1, 1] / scale) * scale, 12)),
    )


def shadow_curvature(rim: np.ndarray, outline_px: np.ndarray, pitch: float, sensor_distance: float) -> np.ndarray:
    """``Q`` (2 × 2) from the aperture's rim points (N, 2; metres, camera frame) and where
    their specular paths land on the sensor (N, 2; pixels): the least-squares affine map
    between them, turned into metres on the sensor in the camera's frame, over ``z2``.

    Examples
    --------
    A plain pinhole, a point 186 mm in front: its shadow is the rim × (1 + z2/z1).

    >>> t = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    >>> rim = 1e-4 * np.stack([np.cos(t), np.sin(t)], -1)
    >>> outline = np.array([1000.0, 600.0]) - rim * (1 + 0.025 / 0.186) / 5.9e-6
    >>> q = shadow_curvature(rim, outline, 5.9e-6, 0.025)
    >>> bool(np.allclose(q, (1 / 0.186 + 1 / 0.025) * np.eye(2)))
    True
    """
    design = np.column_stack([rim, np.ones(len(rim))])
    coefficients, *_ = np.linalg.lstsq(design, outline_px, rcond=None)
    to_pixels = coefficients[:2].T  # pixels per metre of the rim
    return -pitch * to_pixels / sensor_distance

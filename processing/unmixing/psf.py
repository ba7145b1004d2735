"""The camera's point spread: the aperture's geometric image and its diffraction, on the pixel grid."""

from __future__ import annotations

import functools
import math
import threading
import weakref

import numba
import numpy as np
from scipy import fft as sfft


def polygon_area(points: np.ndarray) -> float:
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
def _edge_lines(polygon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def convex_coverage(polygon: np.ndarray, xs: np.ndarray, ys: np.ndarray, sample: float) -> np.ndarray:
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
    """The loop of :func:`convex_coverage`, compiled: per row, the interval where every
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
    to ``reach`` (stored at 0 to ``2 reach``): what :func:`diffract` multiplies by.

    Cached: a run's templates have a few sizes, and a position's five sources share them.
    Read-only.
    """
    offsets = np.arange(-reach, reach + 1) % padded
    kernel = _airy_psf(padded, pitch, aperture, sensor_distance, wavelength)[np.ix_(offsets, offsets)]
    spectrum = sfft.rfft2(kernel, s=(length, length))
    spectrum.flags.writeable = False
    return spectrum


def diffract(
    geometric: np.ndarray,
    size: int,
    margin: int,
    padded: int,
    pitch: float,
    aperture: float,
    sensor_distance: float,
    wavelengths: list[float],
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


def convolve_same(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
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


def convolve_full_each(image: np.ndarray, kernels: list[np.ndarray]) -> np.ndarray:
    """The full linear convolution (``n + k - 1`` a side, by FFT) of one square ``image`` with
    each of ``kernels`` (square, of one size), stacked: the image's transform taken once, and a
    read-only kernel's kept while the kernel lives (the Fresnel kernels are cached and
    read-only, and a run's templates share a few of them, so the rig's fit builds its thousands
    of templates with a third of the transforms)."""
    length = image.shape[0] + kernels[0].shape[0] - 1
    size = sfft.next_fast_len(length, real=True)
    spectrum = sfft.rfft2(image, s=(size, size))
    return np.stack(
        [sfft.irfft2(spectrum * _kernel_spectrum(kernel, size), s=(size, size))[:length, :length] for kernel in kernels]
    )


#: The transforms of read-only kernels: (id, size) → (a weak reference to the kernel, its rfft2).
_SPECTRA: dict[tuple[int, int], tuple[weakref.ref, np.ndarray]] = {}
_SPECTRA_LOCK = threading.Lock()


def _kernel_spectrum(kernel: np.ndarray, size: int) -> np.ndarray:
    key = (id(kernel), size)
    held = _SPECTRA.get(key)
    if held is not None and held[0]() is kernel:  # the same array, not another at its old address
        return held[1]
    spectrum = sfft.rfft2(kernel, s=(size, size))
    if not kernel.flags.writeable:
        with _SPECTRA_LOCK:
            if len(_SPECTRA) >= 128:
                _SPECTRA.pop(next(iter(_SPECTRA)), None)
            _SPECTRA[key] = (weakref.ref(kernel), spectrum)
    return spectrum

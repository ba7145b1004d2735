"""The simulated camera's Fresnel point spread applied to a frame: each channel's band-averaged
point spread (:mod:`~sim_devices.optics.fresnel`) for a point's path, cached, and convolved with
the sharp image of the points that share it.

The sharp image is the pixels' box average (the renderer's sub-pixel samples of the chief rays),
so it is convolved with the point spread sampled at the pixels' centres, not integrated over
them: ``(box ⊗ sharp) ⊗ psf`` sampled on the pixel grid is the pixel-integrated blurred image
exactly while the point spread's band limit lies below the pixels' Nyquist frequency (0.1 cycles
a pixel at the default rig, 0.2 at the demo's).

A path's kernel is cached by (channel, the path rounded): ``Q`` to steps that move the Fresnel
number by at most 0.001 and ``G`` to 0.25 % (the pattern's scale), so that the points of a run,
whose image distances stay within a few millimetres, share a few kernels (the least recently
used dropped past :data:`MAX_KERNELS`).
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from drivers.contracts.rig import Camera
from sim_devices.optics.aperture import ApertureShape
from sim_devices.optics.fresnel import BAND_SAMPLES, PathCurvature, channel_band, fresnel_psf

#: The Fresnel-number step a path is rounded to (half of it is the largest error).
FRESNEL_NUMBER_STEP = 2e-3
#: The relative step ``G`` (the pattern's scale) is rounded to.
CONJUGATE_STEP = 2.5e-3
#: A kernel reaches as far as the Airy pattern's encircled energy leaves this fraction outside;
#: that tail is folded into the kernel (its flux kept, its place approximate, ~1e-5 of the peak).
KERNEL_TAIL = 0.005
#: Kernels kept (single precision; six paths' three channels, 6.4 MB each at the default rig):
#: the default sweep meets 9 paths, going out and back, and computes 12 with six kept.
MAX_KERNELS = 18


@dataclass
class PointSpreadStats:
    """What the cache did: kernels computed, the seconds they took, and kernels reused."""

    computed: int = 0
    seconds: float = 0.0
    reused: int = 0
    keys: list = field(default_factory=list)


class FresnelBlur:
    """Each channel's Fresnel point spread on the camera's pixel grid, by path, cached.

    Parameters
    ----------
    camera : Camera
        The rig's camera: its pitch, sensor distance, bands (:func:`~sim_devices.optics.fresnel.channel_band`).
    aperture : ApertureShape
        The pinhole.
    band_samples : int
        Wavelengths a channel's band is integrated over.
    """

    def __init__(self, camera: Camera, aperture: ApertureShape, band_samples: int = BAND_SAMPLES):
        self.camera = camera
        self.aperture = aperture
        self.bands = [channel_band(camera, ch, band_samples) for ch in range(3)]
        lam_min = min(float(w.min()) for w, _ in self.bands)
        lam_max = max(float(w.max()) for w, _ in self.bands)
        radius = aperture.radius
        self.quadratic_step = FRESNEL_NUMBER_STEP * lam_min / radius**2
        self.conjugate_step = CONJUGATE_STEP * camera.pixel_pitch_m / camera.sensor_distance_m
        g = camera.pixel_pitch_m / camera.sensor_distance_m
        # The Airy pattern leaves 2λ / (π² D g r) of its flux beyond r pixels (for r ≫ λ/Dg).
        self.kernel_radius = int(math.ceil(2.0 * lam_max / (math.pi**2 * 2.0 * radius * g * KERNEL_TAIL)))
        self._kernels: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.stats = PointSpreadStats()

    def rounded(self, path: PathCurvature) -> PathCurvature:
        """The path its kernel is computed for (see the module's docstring)."""
        return path.quantised(self.quadratic_step, self.conjugate_step)

    def kernel(self, channel: int, path: PathCurvature) -> np.ndarray:
        """The point spread of ``path`` (rounded) in ``channel``, sampled at the pixels' centres
        over ``2 · kernel_radius + 1`` pixels a side, the chief ray's point at the centre, its
        period's flux beyond folded in (it sums to 1; single precision)."""
        rounded = self.rounded(path)
        key = (channel, rounded.key)
        cached = self._kernels.get(key)
        if cached is not None:
            self.stats.reused += 1
            self._kernels.move_to_end(key)
            return cached
        start = time.perf_counter()
        wavelengths, weights = self.bands[channel]
        psf = fresnel_psf(self.aperture, wavelengths, rounded, weights=weights, pixel_integrated=False)
        kernel = fold(psf, self.kernel_radius)
        kernel = (kernel / kernel.sum()).astype(np.float32)
        self._kernels[key] = kernel
        if len(self._kernels) > MAX_KERNELS:
            self._kernels.popitem(last=False)
        self.stats.computed += 1
        self.stats.seconds += time.perf_counter() - start
        self.stats.keys.append(key)
        return kernel

    def blur(self, layer: np.ndarray, path: PathCurvature) -> np.ndarray:
        """``layer`` (3, H, W), each channel convolved with its kernel for ``path``; what falls off
        the sensor is lost."""
        out = np.zeros_like(layer)
        lit = np.any(layer != 0, axis=0)
        rows, cols = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
        if rows.size == 0:
            return out
        r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        h = self.kernel_radius
        height, width = layer.shape[1:]
        # The full convolution's (i, j) is the frame's (r0 - h + i, c0 - h + j): clip to the frame.
        top, left = r0 - h, c0 - h
        fr0, fr1 = max(top, 0), min(r1 + h, height)
        fc0, fc1 = max(left, 0), min(c1 + h, width)
        for ch in range(3):
            if not np.any(layer[ch, r0:r1, c0:c1]):
                continue
            full = signal.fftconvolve(layer[ch, r0:r1, c0:c1], self.kernel(ch, path))
            out[ch, fr0:fr1, fc0:fc1] = full[fr0 - top : fr1 - top, fc0 - left : fc1 - left]
        np.clip(out, 0.0, None, out=out)
        return out


def fold(psf: np.ndarray, radius: int) -> np.ndarray:
    """A centred periodic point spread folded onto ``2 · radius + 1`` pixels a side about its
    centre (an offset ``d`` lands on ``d`` modulo the side): the flux is kept."""
    m = psf.shape[0]
    side = 2 * radius + 1
    if side >= m:
        out = np.zeros((side, side))
        start = radius - m // 2
        out[start : start + m, start : start + m] = psf
        return out
    index = (np.arange(m) - m // 2 + radius) % side
    rows = np.zeros((side, m))
    np.add.at(rows, index, psf)
    out = np.zeros((side, side))
    np.add.at(out.T, index, rows.T)
    return out


def led_point_spread(
    camera: Camera, distance_m: float, side: int = 129, peak_e: float | None = None, seed: int = 0
) -> np.ndarray:
    """What a lab measures of ``camera``'s point spread: a small LED ``distance_m`` in front of
    the pinhole, on its axis, imaged per channel on the sensor's pixels (each channel's band,
    pixel-integrated), ``side`` pixels a side about the chief ray, each channel scaled to unit
    sum. With ``peak_e``, the brightest pixel collects that many electrons and each pixel's
    photon and read noise is drawn (``seed``), a dark frame taken off.

    Returns
    -------
    ndarray, shape (3, side, side)
    """
    aperture = ApertureShape.from_rig(camera)
    path = PathCurvature.on_axis(distance_m, camera.sensor_distance_m, camera.pixel_pitch_m)
    images = []
    for channel in range(3):
        wavelengths, weights = channel_band(camera, channel, BAND_SAMPLES)
        psf = fresnel_psf(aperture, wavelengths, path, weights=weights, min_pixels=side)
        middle, half = psf.shape[0] // 2, side // 2
        images.append(psf[middle - half : middle - half + side, middle - half : middle - half + side])
    out = np.stack(images)
    if peak_e is not None:
        rng = np.random.default_rng(seed)
        electrons = out * (peak_e / out.max())
        out = rng.poisson(electrons) + rng.normal(0.0, camera.read_noise_e, out.shape)
    return out / out.sum(axis=(1, 2), keepdims=True)  # a lab knows only what its window holds

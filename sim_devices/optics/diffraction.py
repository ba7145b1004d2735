"""Diffraction: the exact optical transfer function of a circular aperture (the Airy pattern),
applied to a sampled image as a product in the Fourier domain.

The OTF is band-limited well below the pixel Nyquist frequency at the default f/125, so the
FFT product is exact.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import fft as sfft


def circular_otf(fx: np.ndarray, fy: np.ndarray, cutoff: float) -> np.ndarray:
    """Incoherent OTF of a circular aperture (the Fourier transform of the Airy pattern).

    ``cutoff = D / (λ · f)`` cycles per metre on the sensor (Goodman, *Introduction to
    Fourier Optics*, §6.3).
    """
    rho = np.sqrt(fx * fx + fy * fy) / cutoff
    rho = np.clip(rho, 0.0, 1.0)
    return (2.0 / math.pi) * (np.arccos(rho) - rho * np.sqrt(1.0 - rho * rho))


def apply_diffraction(
    image: np.ndarray, pitch: float, aperture_diameter: float, sensor_distance: float, wavelength: float
) -> np.ndarray:
    """Convolve a sampled irradiance image with the Airy pattern of the aperture."""
    h, w = image.shape
    cutoff = aperture_diameter / (wavelength * sensor_distance)
    pad = int(math.ceil(8.0 / (cutoff * pitch)))  # ~8 Airy rings of margin against wrap-around
    ph, pw = sfft.next_fast_len(h + 2 * pad, real=True), sfft.next_fast_len(w + 2 * pad, real=True)
    spectrum = sfft.rfft2(image, s=(ph, pw), workers=-1)
    fy = sfft.fftfreq(ph, d=pitch)[:, None]
    fx = sfft.rfftfreq(pw, d=pitch)[None, :]
    spectrum *= circular_otf(fx, fy, cutoff)
    out = sfft.irfft2(spectrum, s=(ph, pw), workers=-1)
    # The image was placed at the array's origin: wrap-around from the far edge lands in
    # the padding, which is cut away here.
    return np.ascontiguousarray(out[:h, :w])

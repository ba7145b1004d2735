"""Merge a raw exposure bracket into linear radiance with its variance.

The merge works on the Bayer mosaic, before any demosaicing: black level removed per CFA
site, every sample divided by its exposure time, saturated samples rejected at a level
measured from the data (LibRaw's reported white level is often wrong), and the rest
combined with the weights that minimise the variance under a photon-shot-plus-read noise
model.

With a conversion gain ``g`` (e⁻/DN) and read noise ``σ_r`` (DN), a sample of a pixel of
radiance ``X`` (DN/s) exposed for ``t`` has mean ``μ = t X`` and variance
``σ² = μ / g + σ_r²``. The minimum-variance unbiased combination of the estimates
``y_i / t_i`` weights them by ``t_i² / σ_i²`` (Granados et al., "Optimal HDR
reconstruction with linear digital cameras", CVPR 2010; Hanji et al., "Noise-aware merging
of high dynamic range image stacks without camera calibration", ECCV 2020). The variances
are predicted from a first, Poisson-optimal estimate ``Σ y_i / Σ t_i`` (the estimator of
HDRutils, exact when read noise is negligible) rather than from each sample's own value,
which would bias the result; samples whose predicted mean lies within three standard
deviations of saturation are dropped for the same reason.

Methods (``method=``): ``"optimal"`` (the above), ``"poisson"`` (``Σ y / Σ t``), and
``"debevec"`` for 8-bit non-linear brackets (Debevec & Malik, SIGGRAPH 1997, through
OpenCV's ``CalibrateDebevec`` and ``MergeDebevec``).

Modules: :mod:`~processing.hdr.model` (the noise model, the merge's result and error),
:mod:`~processing.hdr.brackets` (the raw and the 8-bit merges), :mod:`~processing.hdr.noise`
(the noise model estimated from the brackets), :mod:`~processing.hdr.mosaic` (the Bayer
mosaic's channels and superpixels).
"""

from processing.hdr.brackets import MERGE_METHODS, RAW_METHODS, measure_saturation, merge, merge_ldr, merge_raw
from processing.hdr.model import HDRError, MergeResult, NoiseModel
from processing.hdr.mosaic import CHANNEL, cfa_channels, superpixels
from processing.hdr.noise import estimate_noise

__all__ = [
    "CHANNEL",
    "MERGE_METHODS",
    "RAW_METHODS",
    "cfa_channels",
    "estimate_noise",
    "measure_saturation",
    "merge",
    "merge_ldr",
    "merge_raw",
    "superpixels",
    "HDRError",
    "MergeResult",
    "NoiseModel",
]

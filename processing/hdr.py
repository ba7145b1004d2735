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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np


class HDRError(ValueError):
    """A bracket that cannot be merged (one line naming the cause)."""


@dataclass(frozen=True)
class NoiseModel:
    """Photon-shot-plus-read noise of a sensor, in digital numbers."""

    gain_e_per_dn: float
    read_noise_dn: float
    source: str = "rig"  # where the figures came from: "rig" or "estimated"

    def variance(self, mean_dn):
        """Variance in DN² of a sample of mean ``mean_dn`` (above black), quantisation included."""
        return np.maximum(mean_dn, 0.0) / self.gain_e_per_dn + self.read_noise_dn**2 + 1.0 / 12.0


@dataclass
class MergeResult:
    """One position's merged bracket, per Bayer site.

    Attributes
    ----------
    radiance : float32 (H, W)
        Signal rate in DN/s above black; NaN where no sample was usable.
    variance : float32 (H, W)
        Variance of ``radiance`` under the noise model, (DN/s)².
    count : uint8 (H, W)
        Frames that contributed to each pixel.
    saturated : bool (H, W)
        Saturated even in the shortest exposure: ``radiance`` is then only a lower bound
        (the shortest frame's value), never an estimate.
    saturation_level : float (2, 2)
        The clipping level measured per CFA site, in raw DN.
    """

    radiance: np.ndarray
    variance: np.ndarray
    count: np.ndarray
    saturated: np.ndarray
    saturation_level: np.ndarray
    noise: NoiseModel
    method: str


# --- saturation, measured ---------------------------------------------------------------------
@numba.njit(parallel=True, cache=True)
def _site_maxima(frames):
    k, h, w = frames.shape
    rows = np.zeros((h, 2), np.int64)
    for y in numba.prange(h):
        for i in range(k):
            for x in range(w):
                v = frames[i, y, x]
                if v > rows[y, x & 1]:
                    rows[y, x & 1] = v
    top = np.zeros((2, 2), np.int64)
    for y in range(h):
        for sx in range(2):
            top[y & 1, sx] = max(top[y & 1, sx], rows[y, sx])
    return top


@numba.njit(parallel=True, cache=True)
def _site_counts(frames, top, window):
    """Per CFA site: samples within ``window`` of the top, and in the 40 windows beneath."""
    k, h, w = frames.shape
    counts = np.zeros((h, 2, 2), np.int64)
    for y in numba.prange(h):
        for i in range(k):
            for x in range(w):
                t = top[y & 1, x & 1]
                v = frames[i, y, x]
                if v > t - window:
                    counts[y, x & 1, 0] += 1
                elif v > t - 41 * window:
                    counts[y, x & 1, 1] += 1
    out = np.zeros((2, 2, 2), np.int64)
    for y in range(h):
        for sx in range(2):
            out[y & 1, sx, 0] += counts[y, sx, 0]
            out[y & 1, sx, 1] += counts[y, sx, 1]
    return out


def measure_saturation(frames: np.ndarray, reported_white: int, *, pile_fraction: float = 1e-4) -> np.ndarray:
    """The raw level at which each CFA site clips, from the data.

    A clipping sensor piles samples up in a spike at its top value, far denser than the
    values just below it (a well-exposed flat field only has a sparse noise tail there).
    Per CFA site: if at least ``pile_fraction`` of the samples lie within a window of
    0.1 % of the range below the highest value, at ten times the density of the 40
    windows beneath, that value is the clipping level; otherwise nothing clipped and the
    reported white level stands.
    """
    frames = np.ascontiguousarray(frames)
    window = max(2, int(0.001 * reported_white))
    top = _site_maxima(frames)
    counts = _site_counts(frames, top, window)
    k, h, w = frames.shape
    levels = np.empty((2, 2))
    for sy in range(2):
        for sx in range(2):
            size = k * len(range(sy, h, 2)) * len(range(sx, w, 2))
            at_top, beneath = counts[sy, sx, 0], counts[sy, sx, 1] / 40.0
            spike = at_top >= pile_fraction * size and at_top > 10.0 * max(beneath, 1.0)
            levels[sy, sx] = top[sy, sx] if spike else reported_white
    return levels


# --- the merge kernels -------------------------------------------------------------------------
# fastmath's reassociation is harmless here: every sum has at most 16 terms, and the
# only non-finite value (inf for saturated pixels) is assigned, never computed with.
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


@numba.njit(parallel=True, cache=True, fastmath=_FAST)
def _merge_kernel(frames, exposures, black, threshold, inv_gain, read_var, near_black, optimal):
    """Row by row; inside a row, loops run along x with the exposure outside, so that
    they read memory contiguously and vectorise."""
    k, h, w = frames.shape
    radiance = np.empty((h, w), np.float32)
    variance = np.empty((h, w), np.float32)
    count = np.zeros((h, w), np.uint8)
    saturated = np.zeros((h, w), np.bool_)
    shortest = np.argmin(exposures)
    inv_t = 1.0 / exposures
    for y in numba.prange(h):
        b = np.empty(w)
        thr = np.empty(w)
        for x in range(w):
            b[x] = black[y & 1, x & 1]
            thr[x] = threshold[y & 1, x & 1]
        sum_y = np.zeros(w)
        sum_t = np.zeros(w)
        n1 = np.zeros(w, np.int64)
        # Pass 1: Poisson-optimal estimate from every unsaturated sample.
        for i in range(k):
            t = exposures[i]
            for x in range(w):
                v = frames[i, y, x]
                if v < thr[x]:
                    sum_y[x] += v - b[x]
                    sum_t[x] += t
                    n1[x] += 1
        x0 = np.empty(w)
        for x in range(w):
            x0[x] = max(sum_y[x] / sum_t[x], 0.0) if n1[x] > 0 else 0.0
        # The longest exposure whose mean stays 3 sigma clear of clipping, per pixel.
        longest = np.full(w, -1, np.int64)
        fallback = np.full(w, -1, np.int64)
        for i in range(k):
            t = exposures[i]
            for x in range(w):
                if frames[i, y, x] >= thr[x]:
                    continue
                if fallback[x] < 0 or t < exposures[fallback[x]]:
                    fallback[x] = i
                mu = t * x0[x]
                if mu + 3.0 * math.sqrt(mu * inv_gain + read_var) < thr[x] - b[x]:
                    if longest[x] < 0 or t > exposures[longest[x]]:
                        longest[x] = i
        # Pass 2: weights t^2 / sigma^2 with sigma^2 predicted from x0, not from each sample.
        num = np.zeros(w)
        den = np.zeros(w)
        n2 = np.zeros(w, np.int64)
        if optimal:
            for i in range(k):
                t = exposures[i]
                for x in range(w):
                    v = frames[i, y, x]
                    if v >= thr[x]:
                        continue
                    mu = t * x0[x]
                    var = mu * inv_gain + read_var
                    if mu + 3.0 * math.sqrt(var) >= thr[x] - b[x]:
                        continue  # its mean is too close to clipping to be unbiased
                    if mu < near_black and i != longest[x]:
                        continue  # all but read noise; a longer exposure says more
                    wgt = t * t / var
                    num[x] += wgt * (v - b[x]) * inv_t[i]
                    den[x] += wgt
                    n2[x] += 1
        for x in range(w):
            if n1[x] == 0:
                # Saturated in every frame: report the shortest frame's lower bound.
                radiance[y, x] = (frames[shortest, y, x] - b[x]) * inv_t[shortest]
                variance[y, x] = np.inf
                saturated[y, x] = True
            elif not optimal:
                radiance[y, x] = sum_y[x] / sum_t[x]
                variance[y, x] = (x0[x] * sum_t[x] * inv_gain + n1[x] * read_var) / (sum_t[x] * sum_t[x])
                count[y, x] = n1[x]
            elif n2[x] == 0:
                # Only samples near clipping remain: keep the shortest unsaturated one.
                j = fallback[x]
                var = exposures[j] * x0[x] * inv_gain + read_var
                radiance[y, x] = (frames[j, y, x] - b[x]) * inv_t[j]
                variance[y, x] = var * inv_t[j] * inv_t[j]
                count[y, x] = 1
            else:
                radiance[y, x] = num[x] / den[x]
                variance[y, x] = 1.0 / den[x]
                count[y, x] = n2[x]
    return radiance, variance, count, saturated


def _as_site_array(value) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    if value.shape == ():
        return np.full((2, 2), float(value))
    if value.shape != (2, 2):
        raise HDRError(f"black level: expected one value or a 2x2 CFA tile, got shape {value.shape}")
    return value


def _check_bracket(frames, exposures) -> tuple[np.ndarray, np.ndarray]:
    frames = [np.asarray(f) for f in frames] if isinstance(frames, (list, tuple)) else frames
    if isinstance(frames, list):
        if not frames:
            raise HDRError("bracket: no frames")
        shapes = {f.shape for f in frames}
        if len(shapes) > 1:
            raise HDRError(f"bracket: frames of different sizes {sorted(shapes)}")
        frames = np.stack(frames)
    if frames.ndim != 3 or frames.shape[0] == 0:
        raise HDRError(f"bracket: expected frames of shape (k, H, W), got {frames.shape}")
    if frames.dtype != np.uint16:
        if np.issubdtype(frames.dtype, np.integer) and frames.min() >= 0 and frames.max() <= 65535:
            frames = frames.astype(np.uint16)
        else:
            raise HDRError(f"bracket: raw frames must be unsigned 16-bit integers, got {frames.dtype}")
    if exposures is None:
        raise HDRError("exposure times: missing from the metadata")
    exposures = np.asarray(exposures, dtype=np.float64).ravel()
    if exposures.size != frames.shape[0]:
        raise HDRError(f"exposure times: {exposures.size} given for {frames.shape[0]} frames")
    if not np.all(np.isfinite(exposures)) or np.any(exposures <= 0):
        raise HDRError(f"exposure times: must be positive and finite, got {exposures.tolist()}")
    return np.ascontiguousarray(frames), exposures


def merge_raw(frames, exposures, black_level, white_level: int, noise: NoiseModel, *, method: str = "optimal",
              saturation_level=None, near_black_sigma: float = 2.0) -> MergeResult:  # fmt: skip
    """Merge one position's raw bracket.

    Parameters
    ----------
    frames : uint16 array (k, H, W) or list of (H, W)
        The raw mosaics of the bracket, any order.
    exposures : sequence of float
        Exposure time of each frame in seconds, as read from the files.
    black_level : float or (2, 2)
        Black level per CFA site.
    white_level : int
        The file's reported white level (only used when nothing clipped).
    noise : NoiseModel
        Gain and read noise; see :func:`estimate_noise` to obtain them from the data.
    method : {"optimal", "poisson"}
        The estimator (see the module's description).
    saturation_level : (2, 2), optional
        Clipping level per site; measured from the frames when omitted.
    near_black_sigma : float
        Samples whose predicted signal is below this many read-noise σ are dropped when a
        longer usable exposure exists.
    """
    if method not in RAW_METHODS:
        raise HDRError(f"method: {method!r} is not one of {sorted(RAW_METHODS)} (use merge_ldr for 'debevec')")
    frames, exposures = _check_bracket(frames, exposures)
    black = _as_site_array(black_level)
    levels = measure_saturation(frames, int(white_level)) if saturation_level is None else _as_site_array(saturation_level)
    # Stay clear of the clipping level by 1 % of the range: a pixel's noise near full well
    # can spread a clipped sensor's values a little below the ADC's top code.
    threshold = levels - 0.01 * (levels - black)
    read_var = noise.read_noise_dn**2 + 1.0 / 12.0
    radiance, variance, count, saturated = _merge_kernel(
        frames, exposures, black, threshold, 1.0 / noise.gain_e_per_dn, read_var,
        near_black_sigma * math.sqrt(read_var), method == "optimal",
    )  # fmt: skip
    return MergeResult(radiance, variance, count, saturated, levels, noise, method)


RAW_METHODS = {"optimal": "minimum-variance weights t²/σ² (Granados 2010, Hanji 2020)",
               "poisson": "Σ y / Σ t, optimal for shot noise alone (HDRutils)"}  # fmt: skip


# --- noise model from the data ------------------------------------------------------------------
def estimate_noise(frames, exposures, black_level, *, saturation_level=None, white_level: int = 65535,
                   bins: int = 24) -> NoiseModel:  # fmt: skip
    """Gain and read noise from a bracket itself, without flat fields or repeated frames.

    For two exposures ``t_a < t_b`` of a static scene, ``d = y_a − (t_a / t_b) y_b`` has
    mean zero and variance ``(1 + r) μ_a / g + (1 + r²) σ_r²`` with ``r = t_a / t_b`` and
    ``μ_a`` the mean of ``y_a``. Binning pixels by ``μ_a`` (estimated from the longer
    frame) and fitting that line over every usable pair gives ``1/g`` and ``σ_r²``.
    """
    frames, exposures = _check_bracket(frames, exposures)
    if frames.shape[0] < 2:
        raise HDRError("noise estimate: needs at least two exposures")
    black = _as_site_array(black_level)
    h, w = frames.shape[1:]
    black_map = np.tile(black, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    levels = measure_saturation(frames, white_level) if saturation_level is None else _as_site_array(saturation_level)
    limit = np.tile(levels - 0.05 * (levels - black), ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    order = np.argsort(exposures)
    rows_x, rows_y, weights = [], [], []
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = exposures[a] / exposures[b]
        ya = frames[a].astype(np.float64) - black_map
        yb = frames[b].astype(np.float64) - black_map
        usable = (frames[a] < limit) & (frames[b] < limit)
        mu_a = r * yb[usable]
        d = ya[usable] - r * yb[usable]
        if mu_a.size < 1000:
            continue
        # Log-spaced bins over the signal range: a mirror ball's frames are mostly dark, and
        # quantile bins would spend themselves on the background.
        top = float(mu_a.max())
        if top <= 20.0:
            continue
        edges = np.concatenate([[-np.inf, 20.0], np.geomspace(20.0, top, bins)[1:]])
        index = np.digitize(mu_a, edges[1:-1])
        for k in range(len(edges) - 1):
            sel = index == k
            n = int(np.count_nonzero(sel))
            if n < 100:
                continue
            rows_x.append([(1 + r) * mu_a[sel].mean(), 1 + r * r])
            rows_y.append(d[sel].var() - (1 + r * r) / 12.0)
            weights.append(math.sqrt(n))
    signal_bins = sum(1 for x, _ in rows_x if x > 100.0)
    if len(rows_y) < 3 or signal_bins < 3:
        # The slope (shot noise) is only measurable over a range of signals well above
        # the read noise; a nearly dark bracket would give any gain at all.
        raise HDRError("noise estimate: not enough unsaturated signal in the bracket")
    # Each bin's variance has a relative error of about sqrt(2 / n), times its own size:
    # weight rows by sqrt(n) over the variance's scale.
    x, y, wgt = np.array(rows_x), np.array(rows_y), np.array(weights)
    scale = wgt / np.maximum(np.abs(y), 1e-6)
    (inv_gain, read_var), *_ = np.linalg.lstsq(x * scale[:, None], y * scale, rcond=None)
    if inv_gain <= 0:
        raise HDRError("noise estimate: no shot noise visible (is the scene static and lit?)")
    return NoiseModel(1.0 / inv_gain, math.sqrt(max(read_var, 0.0)), source="estimated")


# --- views --------------------------------------------------------------------------------------
CHANNEL = {"R": 0, "G": 1, "B": 2}


def superpixels(mosaic: np.ndarray, cfa_pattern: str) -> np.ndarray:
    """(H/2, W/2, 3) RGB from 2x2 CFA tiles, the two greens averaged: the display view."""
    h, w = mosaic.shape
    tiles = mosaic[: h - h % 2, : w - w % 2].reshape(h // 2, 2, w // 2, 2).transpose(0, 2, 1, 3)
    rgb = np.zeros((h // 2, w // 2, 3), dtype=np.float32)
    counts = np.zeros(3)
    for i, colour in enumerate(cfa_pattern):
        rgb[..., CHANNEL[colour]] += tiles[..., i // 2, i % 2]
        counts[CHANNEL[colour]] += 1
    return rgb / counts.astype(np.float32)


# --- 8-bit, non-linear brackets ------------------------------------------------------------------
def merge_ldr(images, exposures, *, samples: int = 70, lambda_: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Debevec & Malik's response recovery and merge for 8-bit brackets (e.g. JPEG).

    Returns the relative radiance (H, W, 3) float32 and the recovered response curve
    (256, 1, 3).
    """
    import cv2

    images = [np.asarray(im) for im in images]
    if not images:
        raise HDRError("bracket: no images")
    if any(im.dtype != np.uint8 for im in images):
        raise HDRError("method 'debevec': needs 8-bit images")
    if len({im.shape for im in images}) > 1:
        raise HDRError(f"bracket: images of different sizes {sorted({im.shape for im in images})}")
    times = np.asarray(exposures, dtype=np.float32)
    if times.size != len(images) or not np.all(times > 0):
        raise HDRError("exposure times: one positive time per image is needed")
    response = cv2.createCalibrateDebevec(samples=samples, lambda_=lambda_).process(images, times)
    radiance = cv2.createMergeDebevec().process(images, times, response)
    return radiance, response


# --- one entry point, named estimators -------------------------------------------------------
def _merge_debevec(images, exposures, **_ignored):
    radiance, _response = merge_ldr(images, exposures)
    return radiance


MERGE_METHODS = {
    "optimal": lambda frames, exposures, **kw: merge_raw(frames, exposures, method="optimal", **kw),
    "poisson": lambda frames, exposures, **kw: merge_raw(frames, exposures, method="poisson", **kw),
    "debevec": _merge_debevec,
}


def merge(frames, exposures, *, method: str = "optimal", **options):
    """Merge a bracket with the named estimator.

    ``"optimal"`` and ``"poisson"`` take raw mosaics and need ``black_level``,
    ``white_level`` and ``noise`` (see :func:`merge_raw`); they return a
    :class:`MergeResult`. ``"debevec"`` takes 8-bit images (JPEG brackets) and returns
    relative radiance (H, W, 3) (see :func:`merge_ldr`).
    """
    try:
        estimator = MERGE_METHODS[method]
    except KeyError:
        raise HDRError(f"method: {method!r} is not one of {sorted(MERGE_METHODS)}") from None
    return estimator(frames, exposures, **options)

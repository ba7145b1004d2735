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

import contextlib
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


# --- threads ------------------------------------------------------------------------------------
_SERIAL_BELOW = 1 << 18  # samples; a parallel launch costs more than it saves below this


@contextlib.contextmanager
def _serial_if_small(samples: int):
    """Run the kernels on the calling thread alone for small inputs: a parallel region waits
    for every worker, and one descheduled on a busy machine stalls it for a time slice or
    more, which dwarfs a sub-millisecond merge. (``numba.set_num_threads`` is per thread.)"""
    threads = numba.get_num_threads()
    if samples >= _SERIAL_BELOW or threads == 1:
        yield
        return
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(threads)


# --- saturation, measured ---------------------------------------------------------------------
# Both passes read a row's even and odd columns as two strided streams (no ``x & 1`` per
# sample), so that they vectorise; the per-row results are reduced afterwards. The second
# pass skips the rows whose maxima lie below its windows (most of a mirror ball's frame).
@numba.njit(parallel=True, cache=True)
def _site_maxima(frames):
    k, h, w = frames.shape
    rows = np.zeros((h, 2), np.int64)
    half = w // 2
    for y in numba.prange(h):
        m0 = 0
        m1 = 0
        for i in range(k):
            row = frames[i, y]
            for x in range(half):
                m0 = max(m0, np.int32(row[2 * x]))
                m1 = max(m1, np.int32(row[2 * x + 1]))
            if w & 1:
                m0 = max(m0, np.int32(row[w - 1]))
        rows[y, 0] = m0
        rows[y, 1] = m1
    top = np.zeros((2, 2), np.int64)
    for y in range(h):
        for sx in range(2):
            top[y & 1, sx] = max(top[y & 1, sx], rows[y, sx])
    return top, rows


@numba.njit(parallel=True, cache=True)
def _site_counts(frames, top, window, rows):
    """Per CFA site: samples within ``window`` of the top, and in the 40 windows beneath
    (``rows``: each row's maximum per column parity, from :func:`_site_maxima`)."""
    k, h, w = frames.shape
    counts = np.zeros((h, 2, 2), np.int64)
    half = w // 2
    for y in numba.prange(h):
        near0 = np.int32(top[y & 1, 0] - window)
        near1 = np.int32(top[y & 1, 1] - window)
        far0 = np.int32(top[y & 1, 0] - 41 * window)
        far1 = np.int32(top[y & 1, 1] - 41 * window)
        if rows[y, 0] <= far0 and rows[y, 1] <= far1:
            continue  # nothing in the windows (counts stay zero)
        a0 = 0
        a1 = 0
        b0 = 0
        b1 = 0
        for i in range(k):
            row = frames[i, y]
            for x in range(half):
                v0 = np.int32(row[2 * x])
                v1 = np.int32(row[2 * x + 1])
                a0 += np.int32(v0 > near0)
                b0 += np.int32(v0 > far0)
                a1 += np.int32(v1 > near1)
                b1 += np.int32(v1 > far1)
            if w & 1:
                v0 = np.int32(row[w - 1])
                a0 += np.int32(v0 > near0)
                b0 += np.int32(v0 > far0)
        counts[y, 0, 0] = a0
        counts[y, 0, 1] = b0 - a0
        counts[y, 1, 0] = a1
        counts[y, 1, 1] = b1 - a1
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
    with _serial_if_small(frames.size):
        top, rows = _site_maxima(frames)
        counts = _site_counts(frames, top, window, rows)
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


_BLOCK = 256  # pixels of a row merged together: their running sums stay in the L1 cache


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")  # no call: no array refcounts
def _merge_pixel(frames, y, x, desc, exposures, inv_t, shortest, thr, b, room, x0, inv_gain, read_var, near_black):
    """Pass 2 of the optimal estimator at one pixel, given its pass-1 estimate ``x0``.

    The frames are visited from the longest exposure down (``desc``), so the first sample
    3 sigma clear of clipping is the longest usable one. Returns (radiance, variance, count).
    """
    k = frames.shape[0]
    num = 0.0
    den = 0.0
    n1 = 0
    n2 = 0
    found = False  # the longest usable sample is already in
    fallback = -1  # the shortest unsaturated frame
    for ii in range(k):
        i = desc[ii]
        v = np.int32(frames[i, y, x])
        if v >= thr:
            continue
        n1 += 1
        t = exposures[i]
        if fallback < 0 or t < exposures[fallback]:
            fallback = i
        mu = t * x0
        var = mu * inv_gain + read_var
        # mu + 3 sigma < room, without the square root
        clear = room - mu
        if not (clear > 0.0 and 9.0 * var < clear * clear):
            continue  # its mean is too close to clipping to be unbiased
        if mu >= near_black or not found:  # near black: all but read noise, unless the longest
            wgt = t * t / var
            num += wgt * (v - b) * inv_t[i]
            den += wgt
            n2 += 1
        found = True
    if n1 == 0:
        # Saturated in every frame: report the shortest frame's lower bound.
        return (frames[shortest, y, x] - b) * inv_t[shortest], np.inf, 0
    if n2 == 0:
        # Only samples near clipping remain: keep the shortest unsaturated one.
        j = fallback
        var = exposures[j] * x0 * inv_gain + read_var
        return (frames[j, y, x] - b) * inv_t[j], var * inv_t[j] * inv_t[j], 1
    return num / den, 1.0 / den, n2


@numba.njit(parallel=True, cache=True, fastmath=_FAST, error_model="numpy")  # x / 0 is no exception
def _merge_kernel(
    frames,
    exposures,
    desc,
    black,
    threshold,
    room,
    inv_gain,
    read_var,
    near_black,
    optimal,
    shortcut,
    radiance,
    variance,
    count,
    saturated,
):
    """Fills ``radiance``, ``variance``, ``count``, ``saturated``.

    ``desc``: the frames in decreasing exposure (ties in index order); ``threshold``: per
    site, the integer a sample must stay below to count as unsaturated; ``room``: the
    threshold above black. Row blocks of ``_BLOCK`` pixels: pass 1 runs along x with the
    exposure outside (contiguous, vectorised); then every pixel gets the "dark" result
    (nothing clipped and every frame but the longest near black, so the longest alone
    counts: most of a mirror ball's frame), and only the others (``shortcut`` False: all)
    go through :func:`_merge_pixel`.
    """
    k, h, w = frames.shape
    shortest = np.argmin(exposures)
    inv_t = 1.0 / exposures
    longest = desc[0]
    t_long = exposures[longest]
    t_next = exposures[desc[1]] if k > 1 else 0.0
    # Per-x constants, for even and odd rows.
    bx = np.empty((2, w))
    tx = np.empty((2, w), np.int32)
    rx = np.empty((2, w))
    for sy in range(2):
        for x in range(w):
            bx[sy, x] = black[sy, x & 1]
            tx[sy, x] = threshold[sy, x & 1]
            rx[sy, x] = room[sy, x & 1]
    chunks = min(h, 64)
    for c in numba.prange(chunks):
        sum_v = np.empty(_BLOCK, np.int32)
        n1 = np.empty(_BLOCK, np.int32)
        sum_t = np.empty(_BLOCK)
        x0 = np.empty(_BLOCK)
        dark = np.empty(_BLOCK, np.bool_)
        for y in range(c * h // chunks, (c + 1) * h // chunks):
            sy = y & 1
            for xs in range(0, w, _BLOCK):
                n = min(_BLOCK, w - xs)
                b = bx[sy, xs : xs + n]
                thr = tx[sy, xs : xs + n]
                lim = rx[sy, xs : xs + n]
                rad = radiance[y, xs : xs + n]
                var_out = variance[y, xs : xs + n]
                cnt = count[y, xs : xs + n]
                sat = saturated[y, xs : xs + n]
                # Pass 1: Poisson-optimal estimate from every unsaturated sample.
                sum_v[:n] = 0
                n1[:n] = 0
                sum_t[:n] = 0.0
                for i in range(k):
                    t = exposures[i]
                    row = frames[i, y, xs : xs + n]
                    for j in range(n):
                        v = np.int32(row[j])
                        u = v < thr[j]
                        sum_v[j] += v if u else 0
                        n1[j] += 1 if u else 0
                        sum_t[j] += t if u else 0.0
                if not optimal:
                    row = frames[shortest, y, xs : xs + n]
                    for j in range(n):
                        sum_y = sum_v[j] - n1[j] * b[j]
                        if n1[j] == 0:
                            # Saturated in every frame: report the shortest frame's lower bound.
                            rad[j] = (row[j] - b[j]) * inv_t[shortest]
                            var_out[j] = np.inf
                        else:
                            m = max(sum_y / sum_t[j], 0.0)
                            rad[j] = sum_y / sum_t[j]
                            var_out[j] = (m * sum_t[j] * inv_gain + n1[j] * read_var) / (sum_t[j] * sum_t[j])
                        cnt[j] = n1[j]
                        sat[j] = n1[j] == 0
                    continue
                # Pass 2 where only the longest frame counts, assumed everywhere, then the
                # other pixels redone: weights t^2 / sigma^2 with sigma^2 predicted from x0.
                row = frames[longest, y, xs : xs + n]
                rest = 0
                for j in range(n):
                    m = max((sum_v[j] - n1[j] * b[j]) / sum_t[j], 0.0) if n1[j] > 0 else 0.0
                    x0[j] = m
                    mu = t_long * m
                    var = mu * inv_gain + read_var
                    clear = lim[j] - mu
                    simple = (n1[j] == k) & (clear > 0.0) & (9.0 * var < clear * clear) & (t_next * m < near_black)
                    dark[j] = simple
                    rest += 0 if simple else 1
                    rad[j] = (row[j] - b[j]) * inv_t[longest]
                    var_out[j] = var * inv_t[longest] * inv_t[longest]
                    cnt[j] = 1
                    sat[j] = False
                if rest or not shortcut:
                    for j in range(n):
                        if not (dark[j] and shortcut):
                            r, vr, nn = _merge_pixel(
                                frames,
                                y,
                                xs + j,
                                desc,
                                exposures,
                                inv_t,
                                shortest,
                                thr[j],
                                b[j],
                                lim[j],
                                x0[j],
                                inv_gain,
                                read_var,
                                near_black,
                            )
                            rad[j] = r
                            var_out[j] = vr
                            cnt[j] = nn
                            sat[j] = nn == 0


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


def merge_raw(
    frames,
    exposures,
    black_level,
    white_level: int,
    noise: NoiseModel,
    *,
    method: str = "optimal",
    saturation_level=None,
    near_black_sigma: float = 2.0,
) -> MergeResult:
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
    with _serial_if_small(frames.size):
        if saturation_level is None:
            levels = measure_saturation(frames, int(white_level))
        else:
            levels = _as_site_array(saturation_level)
        # Stay clear of the clipping level by 1 % of the range: a pixel's noise near full well
        # can spread a clipped sensor's values a little below the ADC's top code.
        threshold = levels - 0.01 * (levels - black)
        read_var = noise.read_noise_dn**2 + 1.0 / 12.0
        radiance, variance, count, saturated = _run_merge(
            frames,
            exposures,
            black,
            threshold,
            1.0 / noise.gain_e_per_dn,
            read_var,
            near_black_sigma * math.sqrt(read_var),
            method == "optimal",
        )
    return MergeResult(radiance, variance, count, saturated, levels, noise, method)


def _run_merge(frames, exposures, black, threshold, inv_gain, read_var, near_black, optimal, *, shortcut=True):
    """The merge kernel on a checked bracket; ``shortcut=False`` takes the general path everywhere."""
    k, h, w = frames.shape
    # An integer sample is below the (float) threshold iff it is below its ceiling.
    below = np.where(np.isnan(threshold), -1, np.clip(np.ceil(threshold), -1, 65536)).astype(np.int32)
    desc = np.argsort(-exposures, kind="stable")  # longest first, ties in index order
    # Allocated by numpy (which asks Linux for huge pages) rather than in the kernel: the
    # first touch of these large outputs is cheaper, and its cost varies less.
    out = (
        np.empty((h, w), np.float32),
        np.empty((h, w), np.float32),
        np.empty((h, w), np.uint8),
        np.empty((h, w), np.bool_),
    )
    _merge_kernel(
        frames,
        exposures,
        desc,
        black,
        below,
        threshold - black,
        inv_gain,
        read_var,
        near_black,
        optimal,
        shortcut,
        *out,
    )
    return out


RAW_METHODS = {
    "optimal": "minimum-variance weights t²/σ² (Granados 2010, Hanji 2020)",
    "poisson": "Σ y / Σ t, optimal for shot noise alone (HDRutils)",
}


# --- noise model from the data ------------------------------------------------------------------
@numba.njit(parallel=True, cache=True)
def _pair_sums(frames, a, b, usable_below, dark_below, shift, centre, chunks):
    """Sums over the usable pixels of frames ``a`` (shorter) and ``b`` (longer), per CFA site.

    A pixel is usable when both samples are below ``usable_below``. Those whose sum
    ``a + b`` is below ``dark_below`` (μ_a surely in the first bin: most of a mirror ball's
    frame) only add to six per-site sums (vectorised): n, Σa, Σb, Σa², Σb², Σab with
    a, b shifted by ``shift``. The others go to a histogram over (site, a + b) of
    n, Σa', Σa'², a' = a − ``centre[site, a + b]`` (integers, exact; a' stays small).
    """
    k, h, w = frames.shape
    levels = centre.shape[2]
    chunks = max(1, min(h, chunks))  # one set of sums per thread
    dark = np.zeros((chunks, 2, 2, 6), np.int64)
    hist = np.zeros((chunks, 2, 2, levels, 3), np.int64)
    half = w // 2
    for c in numba.prange(chunks):
        for y in range(c * h // chunks, (c + 1) * h // chunks):
            sy = y & 1
            ra = frames[a, y]
            rb = frames[b, y]
            lim0 = usable_below[sy, 0]
            lim1 = usable_below[sy, 1]
            dk0 = dark_below[sy, 0]
            dk1 = dark_below[sy, 1]
            s0 = shift[sy, 0]
            s1 = shift[sy, 1]
            n0 = 0
            sa0 = 0
            sb0 = 0
            saa0 = 0
            sbb0 = 0
            sab0 = 0
            n1 = 0
            sa1 = 0
            sb1 = 0
            saa1 = 0
            sbb1 = 0
            sab1 = 0
            rest = 0
            for x in range(half):
                va = np.int64(ra[2 * x])
                vb = np.int64(rb[2 * x])
                use = (va < lim0) & (vb < lim0)
                m = use & (va + vb < dk0)
                rest += np.int64(use) - np.int64(m)
                da = va - s0 if m else 0
                db = vb - s0 if m else 0
                n0 += np.int64(m)
                sa0 += da
                sb0 += db
                saa0 += da * da
                sbb0 += db * db
                sab0 += da * db
                va = np.int64(ra[2 * x + 1])
                vb = np.int64(rb[2 * x + 1])
                use = (va < lim1) & (vb < lim1)
                m = use & (va + vb < dk1)
                rest += np.int64(use) - np.int64(m)
                da = va - s1 if m else 0
                db = vb - s1 if m else 0
                n1 += np.int64(m)
                sa1 += da
                sb1 += db
                saa1 += da * da
                sbb1 += db * db
                sab1 += da * db
            if w & 1:
                va = np.int64(ra[w - 1])
                vb = np.int64(rb[w - 1])
                use = (va < lim0) & (vb < lim0)
                if use and va + vb < dk0:
                    da = va - s0
                    db = vb - s0
                    n0 += 1
                    sa0 += da
                    sb0 += db
                    saa0 += da * da
                    sbb0 += db * db
                    sab0 += da * db
                elif use:
                    rest += 1
            sums = dark[c, sy]
            sums[0, 0] += n0
            sums[0, 1] += sa0
            sums[0, 2] += sb0
            sums[0, 3] += saa0
            sums[0, 4] += sbb0
            sums[0, 5] += sab0
            sums[1, 0] += n1
            sums[1, 1] += sa1
            sums[1, 2] += sb1
            sums[1, 3] += saa1
            sums[1, 4] += sbb1
            sums[1, 5] += sab1
            if rest:
                for x in range(w):
                    sx = x & 1
                    va = np.int64(ra[x])
                    vb = np.int64(rb[x])
                    lim = usable_below[sy, sx]
                    if va < lim and vb < lim and va + vb >= dark_below[sy, sx]:
                        d = va - centre[sy, sx, va + vb]
                        cell = hist[c, sy, sx, va + vb]
                        cell[0] += 1
                        cell[1] += d
                        cell[2] += d * d
    return dark, hist


#: The share of the usable range (black to the clipping limit) within which a pair's expected
#: longer sample must lie for :func:`_pair_bins` to use it: 4 σ of shot noise is 3 % of the
#: range at 20 000 e⁻ full well, 13 % at 1000 e⁻.
_CLEAR_OF_LIMIT = 0.85


def _pair_bins(frames, a, b, r, black, limit, bins):
    """Per log-spaced bin of μ_a: pixel count, mean μ_a and variance of ``d`` (None: pair unusable).

    Pixels are binned by the pair's sum ``y_a + y_b`` (as μ_a = r (y_a + y_b) / (1 + r)),
    which under shot noise is uncorrelated with ``d = y_a − r y_b`` (Cov = σ_a² − r σ_b² = 0),
    so the binning leaves d's variance alone. Binning by ``y_b`` alone, as before 2026-11-22,
    conditioned d on one of its own terms: the variance then depended on the scene's spread
    of signals, and the gain came out 9 % high on a scene of three flat levels.

    The same statistics as binning every usable pixel, from :func:`_pair_sums`: a pixel's
    μ_a depends only on its site and sum, so each histogram cell falls in one bin; within a
    cell ``d = (1 + r) y_a − r (y_a + y_b)`` is affine in ``a``, and the cells' (and the dark
    sums') means and centred sums of squares combine exactly.
    """
    # An integer sample is below a (float) limit iff it is below its ceiling.
    usable_below = np.where(np.isnan(limit), 0, np.clip(np.ceil(limit), 0, 65536)).astype(np.int64)
    # a + b − 2 black < 20 (1 + r) / r, so μ_a < 20: the first bin's.
    dark_below = np.where(np.isnan(black), 0, np.clip(np.ceil(2.0 * black + 20.0 * (1.0 + r) / r), 0, 2 * 65536))
    dark_below = dark_below.astype(np.int64)
    shift = np.where(np.isnan(black), 0, np.clip(np.rint(black), 0, 65536)).astype(np.int64)
    levels = 2 * int(usable_below.max())  # every usable sum is below it
    share = r / (1.0 + r)  # of the sum above black, a's expected part
    sums = np.arange(levels, dtype=np.float64)
    centre = shift[..., None] + np.rint(share * (sums - 2 * shift[..., None])).astype(np.int64)
    dark, hist = _pair_sums(frames, a, b, usable_below, dark_below, shift, centre, numba.get_num_threads())
    dark, hist = dark.sum(axis=0), hist.sum(axis=0)
    sy, sx, v = np.nonzero(hist[..., 0])
    beta = black[sy, sx]
    total = v.astype(np.float64) - 2.0 * beta  # y_a + y_b
    # Near the clipping limit only the pairs with b below it are usable, and those cut d's
    # distribution short within a sum: keep the sums whose expected b is clear of it.
    clear = total / (1.0 + r) < _CLEAR_OF_LIMIT * (limit[sy, sx] - beta)
    sy, sx, v, beta, total = sy[clear], sx[clear], v[clear], beta[clear], total[clear]
    cells = hist[sy, sx, v].astype(np.float64)
    n, sum_a, sum_aa = cells[:, 0], cells[:, 1], cells[:, 2]
    mu = share * total
    mean_d = (1.0 + r) * (sum_a / n + centre[sy, sx, v] - beta) - r * total
    m2 = (1.0 + r) ** 2 * (sum_aa - sum_a * sum_a / n)
    if n.sum() + dark[..., 0].sum() < 1000:
        return None
    # Log-spaced bins over the signal range: a mirror ball's frames are mostly dark, and
    # quantile bins would spend themselves on the background.
    top = float(mu.max()) if mu.size else -np.inf  # the dark pixels' μ_a are all below 20
    if top <= 20.0:
        return None
    edges = np.concatenate([[-np.inf, 20.0], np.geomspace(20.0, top, bins)[1:]])
    index = np.digitize(mu, edges[1:-1])
    # The dark sums, one cell per site, all in the first bin.
    nd = dark[..., 0].ravel().astype(np.float64)
    sa, sb, saa, sbb, sab = (dark[..., i].ravel().astype(np.float64) for i in range(1, 6))
    keep = nd > 0
    nd, sa, sb, saa, sbb, sab = nd[keep], sa[keep], sb[keep], saa[keep], sbb[keep], sab[keep]
    delta = (shift - black).ravel()[keep]  # y = sample − shift + delta
    e = sa - r * sb  # Σ (a − r b), shifted samples
    n = np.concatenate([n, nd])
    mu = np.concatenate([mu, share * ((sa + sb) / nd + 2.0 * delta)])
    mean_d = np.concatenate([mean_d, e / nd + delta * (1.0 - r)])
    m2 = np.concatenate([m2, saa - 2.0 * r * sab + r * r * sbb - e * e / nd])
    index = np.concatenate([index, np.zeros(nd.size, np.int64)])
    count = np.bincount(index, n, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_mu = np.bincount(index, n * mu, minlength=bins) / count
        mean = np.bincount(index, n * mean_d, minlength=bins) / count
        var = np.bincount(index, m2 + n * (mean_d - mean[index]) ** 2, minlength=bins) / count
    return count, mean_mu, var


def estimate_noise(
    frames, exposures, black_level, *, saturation_level=None, white_level: int = 65535, bins: int = 24
) -> NoiseModel:
    """Gain and read noise from a bracket itself, without flat fields or repeated frames.

    For two exposures ``t_a < t_b`` of a static scene, ``d = y_a − (t_a / t_b) y_b`` has
    mean zero and variance ``(1 + r) μ_a / g + (1 + r²) σ_r²`` with ``r = t_a / t_b`` and
    ``μ_a`` the mean of ``y_a``. Binning pixels by ``μ_a`` (estimated from the pair's sum,
    which leaves d's variance unconditioned: :func:`_pair_bins`) and fitting that line over
    every usable pair gives ``1/g`` and ``σ_r²``.
    """
    frames, exposures = _check_bracket(frames, exposures)
    if frames.shape[0] < 2:
        raise HDRError("noise estimate: needs at least two exposures")
    black = _as_site_array(black_level)
    levels = measure_saturation(frames, white_level) if saturation_level is None else _as_site_array(saturation_level)
    limit = levels - 0.05 * (levels - black)
    order = np.argsort(exposures)
    rows_x, rows_y, weights = [], [], []
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = exposures[a] / exposures[b]
        with _serial_if_small(2 * frames[0].size):
            binned = _pair_bins(frames, int(a), int(b), r, black, limit, bins)
        if binned is None:
            continue
        for n, mu, var in zip(*binned, strict=True):
            if n < 100:
                continue
            rows_x.append([(1 + r) * mu, 1 + r * r])
            rows_y.append(var - (1 + r * r) / 12.0)
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


@numba.njit(inline="always")
def _sample(value, replace_nonfinite, replacement):
    x = np.float64(value)
    return replacement if replace_nonfinite and not np.isfinite(x) else x


@numba.njit(parallel=True, cache=True)
def _bayer_superpixels(mosaic, at, rgb, replace_nonfinite, replacement):
    """``rgb`` from a Bayer mosaic whose 2x2 tile has R, G, G, B at ``at`` (4 x (dy, dx)),
    non-finite samples read as ``replacement`` if ``replace_nonfinite``.

    The same float32 arithmetic as numpy's ``rgb += ...; rgb / counts``: a float32 sum of
    two samples is rounded once, and halving is exact.
    """
    h2, w2 = rgb.shape[0], rgb.shape[1]
    for y in numba.prange(h2):
        red = mosaic[2 * y + at[0, 0]]
        green1 = mosaic[2 * y + at[1, 0]]
        green2 = mosaic[2 * y + at[2, 0]]
        blue = mosaic[2 * y + at[3, 0]]
        rx, g1x, g2x, bx = at[0, 1], at[1, 1], at[2, 1], at[3, 1]
        out = rgb[y]
        for x in range(w2):
            out[x, 0] = np.float32(0.0 + _sample(red[2 * x + rx], replace_nonfinite, replacement))
            green = np.float32(0.0 + _sample(green1[2 * x + g1x], replace_nonfinite, replacement))
            green = np.float32(np.float64(green) + _sample(green2[2 * x + g2x], replace_nonfinite, replacement))
            out[x, 1] = green / np.float32(2.0)
            out[x, 2] = np.float32(0.0 + _sample(blue[2 * x + bx], replace_nonfinite, replacement))


def superpixels(mosaic: np.ndarray, cfa_pattern: str, nonfinite: float | None = None) -> np.ndarray:
    """(H/2, W/2, 3) RGB from 2x2 CFA tiles, the two greens averaged: the display view.

    ``nonfinite``: the value a non-finite sample (no estimate) counts as, e.g. 0 for an
    image file; by default NaN and inf carry through. Done in the same pass (a separate
    ``np.where`` over the mosaic cost 3.5 ms at 2000x1312, three times the view itself).
    """
    mosaic = np.asarray(mosaic)
    h, w = mosaic.shape
    if sorted(cfa_pattern) == ["B", "G", "G", "R"] and mosaic.dtype.kind in "fiu":
        at = np.array([divmod(i, 2) for i in sorted(range(4), key=lambda i: CHANNEL[cfa_pattern[i]])], np.int64)
        rgb = np.empty((h // 2, w // 2, 3), np.float32)
        with _serial_if_small(mosaic.size):
            _bayer_superpixels(mosaic, at, rgb, nonfinite is not None, 0.0 if nonfinite is None else float(nonfinite))
        return rgb
    if nonfinite is not None and mosaic.dtype.kind == "f":
        mosaic = np.where(np.isfinite(mosaic), mosaic, mosaic.dtype.type(nonfinite))
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

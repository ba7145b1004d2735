"""The merge of a raw exposure bracket into linear radiance with its variance (see :mod:`processing.hdr`)."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeAlias

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike

from processing.hdr.model import HDRError, MergeResult, NoiseModel

#: A bracket's raw mosaics: one (k, H, W) array, or a list (or tuple) of (H, W) arrays.
Frames: TypeAlias = np.ndarray | list[np.ndarray] | tuple[np.ndarray, ...]

_SERIAL_BELOW = 1 << 18  # samples; a parallel launch costs more than it saves below this


@contextlib.contextmanager
def serial_if_small(samples: int) -> Iterator[None]:
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
    with serial_if_small(frames.size):
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

    Kept whole: both passes over a row block share its scratch arrays inside one parallel
    loop, which numba compiles into one loop nest; the per-pixel step is already a function
    of its own (:func:`_merge_pixel`, inlined).
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


def as_site_array(value: ArrayLike) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    if value.shape == ():
        return np.full((2, 2), float(value))
    if value.shape != (2, 2):
        raise HDRError(f"black level: expected one value or a 2x2 CFA tile, got shape {value.shape}")
    return value


def check_bracket(frames: Frames, exposures: ArrayLike | None) -> tuple[np.ndarray, np.ndarray]:
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
    frames: Frames,
    exposures: ArrayLike,
    black_level: ArrayLike,
    white_level: int,
    noise: NoiseModel,
    *,
    method: str = "optimal",
    saturation_level: ArrayLike | None = None,
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
    frames, exposures = check_bracket(frames, exposures)
    black = as_site_array(black_level)
    with serial_if_small(frames.size):
        if saturation_level is None:
            levels = measure_saturation(frames, int(white_level))
        else:
            levels = as_site_array(saturation_level)
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


def merge_ldr(
    images: Sequence[np.ndarray], exposures: ArrayLike, *, samples: int = 70, lambda_: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """Debevec & Malik's response recovery and merge for 8-bit brackets (e.g. JPEG).

    Returns the relative radiance (H, W, 3) float32 and the recovered response curve
    (256, 1, 3).
    """

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


def _merge_debevec(images: Sequence[np.ndarray], exposures: ArrayLike, **_ignored: object) -> np.ndarray:
    radiance, _response = merge_ldr(images, exposures)
    return radiance


MERGE_METHODS: dict[str, Callable[..., MergeResult | np.ndarray]] = {
    "optimal": lambda frames, exposures, **kw: merge_raw(frames, exposures, method="optimal", **kw),
    "poisson": lambda frames, exposures, **kw: merge_raw(frames, exposures, method="poisson", **kw),
    "debevec": _merge_debevec,
}


def merge(frames: Frames, exposures: ArrayLike, *, method: str = "optimal", **options: Any) -> MergeResult | np.ndarray:
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

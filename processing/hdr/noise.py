"""The noise model (conversion gain and read noise) estimated from the brackets themselves."""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import ArrayLike

from processing.hdr.brackets import Frames, as_site_array, check_bracket, measure_saturation, serial_if_small
from processing.hdr.model import HDRError, NoiseModel


@numba.njit(parallel=True, cache=True)
def _pair_sums(frames, a, b, usable_below, dark_below, shift, centre, chunks):
    """Sums over the usable pixels of frames ``a`` (shorter) and ``b`` (longer), per CFA site.

    A pixel is usable when both samples are below ``usable_below``. Those whose sum
    ``a + b`` is below ``dark_below`` (μ_a surely in the first bin: most of a mirror ball's
    frame) only add to six per-site sums (vectorised): n, Σa, Σb, Σa², Σb², Σab with
    a, b shifted by ``shift``. The others go to a histogram over (site, a + b) of
    n, Σa', Σa'², a' = a − ``centre[site, a + b]`` (integers, exact; a' stays small).

    Kept whole: one parallel loop over row chunks, each with its own sums, which numba
    compiles into one loop nest; split into functions, the per-row sums would have to be
    passed back and forth through arrays.
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
    so the binning leaves d's variance alone. Binning by ``y_b`` alone would condition d on
    one of its own terms: the variance would then depend on the scene's spread of signals
    (the gain comes out 9 % high on a scene of three flat levels).

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
    frames: Frames,
    exposures: ArrayLike,
    black_level: ArrayLike,
    *,
    saturation_level: ArrayLike | None = None,
    white_level: int = 65535,
    bins: int = 24,
) -> NoiseModel:
    """Gain and read noise from a bracket itself, without flat fields or repeated frames.

    For two exposures ``t_a < t_b`` of a static scene, ``d = y_a − (t_a / t_b) y_b`` has
    mean zero and variance ``(1 + r) μ_a / g + (1 + r²) σ_r²`` with ``r = t_a / t_b`` and
    ``μ_a`` the mean of ``y_a``. Binning pixels by ``μ_a`` (estimated from the pair's sum,
    which leaves d's variance unconditioned: :func:`_pair_bins`) and fitting that line over
    every usable pair gives ``1/g`` and ``σ_r²``.
    """
    frames, exposures = check_bracket(frames, exposures)
    if frames.shape[0] < 2:
        raise HDRError("noise estimate: needs at least two exposures")
    black = as_site_array(black_level)
    levels = measure_saturation(frames, white_level) if saturation_level is None else as_site_array(saturation_level)
    limit = levels - 0.05 * (levels - black)
    order = np.argsort(exposures)
    rows_x, rows_y, weights = [], [], []
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = exposures[a] / exposures[b]
        with serial_if_small(2 * frames[0].size):
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

"""The HDR merge against the noise model it assumes: bias, variance, and its edge cases.

Brackets come from the simulated sensor (Poisson shot noise, Gaussian read noise, 12-bit
quantisation, black level, clipping), with the radiance known exactly.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from processing.hdr.brackets import measure_saturation, merge_ldr, merge_raw
from processing.hdr.model import HDRError, NoiseModel
from processing.hdr.mosaic import superpixels
from processing.hdr.noise import estimate_noise
from sim_devices.sensor import SensorModel

SENSOR = SensorModel(full_well_e=20000, read_noise_e=3.0, black_level_dn=64, white_level_dn=4095, cfa_pattern="RGGB")
GAIN = SENSOR.gain_e_per_dn
NOISE = NoiseModel(GAIN, 3.0 / GAIN)
EXPOSURES = np.array([1e-4, 4e-4, 1.6e-3, 6.4e-3, 2.56e-2])


def bracket(rate_e, rng, exposures=EXPOSURES, sensor=SENSOR):
    rgb = np.broadcast_to(rate_e, (3, *rate_e.shape))
    return np.stack([sensor.expose(rgb, t, rng) for t in exposures])


def optimal_variance(x_dn, exposures, threshold_dn):
    """1 / Σ t² / σ² over the samples whose mean stays clear of clipping (DN/s)²."""
    total = np.zeros_like(x_dn)
    for t in exposures:
        mu = t * x_dn
        var = mu / GAIN + NOISE.read_noise_dn**2 + 1 / 12
        usable = mu + 3 * np.sqrt(var) < threshold_dn
        total += np.where(usable, t * t / var, 0.0)
    return 1.0 / total


def hat_merge(frames, exposures, black=64, white=4095):
    """Debevec & Malik's hat weighting with a linear response, for comparison."""
    z = frames.astype(float)
    w = np.minimum(z - black, white - z).clip(min=0)
    w[z >= 0.99 * white] = 0
    return (w * (z - black) / exposures[:, None, None]).sum(0) / w.sum(0)


def test_merge_is_unbiased_over_the_unsaturated_range():
    rng = np.random.default_rng(1)
    rate = np.exp(rng.uniform(math.log(3e2), math.log(2e8), (400, 600)))  # e-/s
    result = merge_raw(bracket(rate, rng), EXPOSURES, 64, 4095, NOISE)
    truth = rate / GAIN
    unsaturated = truth * EXPOSURES[0] < 0.9 * (4095 - 64)
    rel = (result.radiance - truth) / truth
    assert not result.saturated[unsaturated].any()
    assert abs(rel[unsaturated].mean()) < 0.005
    # ... and in every decade of radiance, not only on average.
    decades = np.floor(np.log10(rate[unsaturated]))
    for d in np.unique(decades):
        sel = decades == d
        assert abs(rel[unsaturated][sel].mean()) < 0.005, d
    assert np.all(result.count[unsaturated] >= 1)


@pytest.fixture(scope="module")
def repeated():
    """60 noise realisations of one 24 x 40 scene spanning the bracket's range."""
    rng = np.random.default_rng(2)
    rate = np.geomspace(1e3, 3e8, 24 * 40).reshape(24, 40)
    runs = [bracket(rate, rng) for _ in range(60)]
    return rate / GAIN, runs


def test_variance_matches_the_optimal_estimator_and_beats_hat_weighting(repeated):
    truth, runs = repeated
    ours = np.stack([merge_raw(f, EXPOSURES, 64, 4095, NOISE).radiance for f in runs])
    reported = np.mean([merge_raw(f, EXPOSURES, 64, 4095, NOISE).variance for f in runs[:10]], axis=0)
    hat = np.stack([hat_merge(f, EXPOSURES) for f in runs])
    empirical = ours.var(axis=0, ddof=1)
    predicted = optimal_variance(truth, EXPOSURES, 0.99 * (4095 - 64))
    valid = truth * EXPOSURES[0] < 0.9 * (4095 - 64)
    # Bin by radiance so each comparison averages ~90 pixels x 60 realisations.
    order = np.argsort(truth[valid])
    for chunk in np.array_split(order, 10):
        ratio = empirical[valid][chunk].mean() / predicted[valid][chunk].mean()
        assert ratio == pytest.approx(1.0, abs=0.10), ratio
        assert reported[valid][chunk].mean() / predicted[valid][chunk].mean() == pytest.approx(1.0, abs=0.10)
    hat_var = hat.var(axis=0, ddof=1)
    ratios = np.array([empirical[valid][c].mean() / hat_var[valid][c].mean() for c in np.array_split(order, 10)])
    assert np.all(ratios < 1.02), ratios  # never worse than hat weighting
    assert ratios.mean() < 0.85, ratios  # and lower over the range (most in the dark half)


def test_saturation_is_measured_from_the_data_not_the_reported_white_level():
    rng = np.random.default_rng(3)
    clipped = SensorModel(20000, 3.0, 64, 3900, "RGGB")  # clips at 3900; the file will claim 4095
    rate = np.exp(rng.uniform(math.log(1e3), math.log(1e8), (200, 300)))
    frames = bracket(rate, rng, sensor=clipped)
    levels = measure_saturation(frames, reported_white=4095)
    np.testing.assert_array_equal(levels, np.full((2, 2), 3900))
    result = merge_raw(frames, EXPOSURES, 64, 4095, NoiseModel(clipped.gain_e_per_dn, 3.0 / clipped.gain_e_per_dn))
    truth = rate / clipped.gain_e_per_dn
    ok = truth * EXPOSURES[0] < 0.9 * (3900 - 64)
    rel = (result.radiance[ok] - truth[ok]) / truth[ok]
    assert abs(rel.mean()) < 0.005
    # No leaking highlights: clipped samples kept would show as large errors in bright pixels.
    bright = truth * EXPOSURES[-1] > 2000
    worst = np.abs(result.radiance[bright] - truth[bright]) / np.sqrt(result.variance[bright])
    assert worst.max() < 6.0


def test_a_pixel_saturated_in_every_frame_is_flagged_not_filled():
    rng = np.random.default_rng(4)
    rate = np.full((8, 8), 1e5)
    rate[3, 4] = 1e12  # saturates even 0.1 ms
    result = merge_raw(bracket(rate, rng), EXPOSURES, 64, 4095, NOISE)
    assert result.saturated[3, 4] and result.saturated.sum() == 1
    assert result.count[3, 4] == 0 and math.isinf(result.variance[3, 4])
    # The lower bound from the shortest frame, not a guess.
    assert result.radiance[3, 4] == pytest.approx((4095 - 64) / EXPOSURES[0])


def test_single_frame_bracket_is_its_own_estimate():
    rng = np.random.default_rng(5)
    frame = bracket(np.full((10, 12), 2e6), rng, exposures=[0.001])
    result = merge_raw(frame, [0.001], 64, 4095, NOISE)
    np.testing.assert_allclose(result.radiance, (frame[0].astype(float) - 64) / 0.001, rtol=1e-6)
    assert np.all(result.count == 1)


@pytest.mark.parametrize(
    ("frames", "exposures", "message"),
    [
        ([np.zeros((4, 6), np.uint16), np.zeros((4, 8), np.uint16)], [0.1, 0.2], r"bracket: frames of different sizes"),
        (np.zeros((2, 4, 6), np.uint16), None, r"exposure times: missing from the metadata"),
        (np.zeros((2, 4, 6), np.uint16), [0.1], r"exposure times: 1 given for 2 frames"),
        (np.zeros((2, 4, 6), np.uint16), [0.1, float("nan")], r"exposure times: must be positive and finite"),
        (np.zeros((2, 4, 6), np.float32), [0.1, 0.2], r"raw frames must be unsigned 16-bit"),
        ([], [], r"bracket: no frames"),
    ],
)
def test_bad_brackets_get_one_line_errors(frames, exposures, message):
    with pytest.raises(HDRError, match=message) as caught:
        merge_raw(frames, exposures, 64, 4095, NOISE)
    assert "\n" not in str(caught.value)


def test_unknown_method_is_refused():
    with pytest.raises(HDRError, match=r"method: 'debevec' is not one of \['optimal', 'poisson'\]"):
        merge_raw(np.zeros((1, 4, 4), np.uint16), [0.1], 64, 4095, NOISE, method="debevec")


def test_the_noise_estimate_does_not_depend_on_the_spread_of_signals():
    """A scene of three flat levels: binned by the longer sample, pixels of one level would
    fall in bins by their own noise and d's variance with them (the gain came out 8.6 % high);
    binned by the pair's sum, which is uncorrelated with d, within 1 %."""
    rng = np.random.default_rng(21)
    rate = np.array([3e4, 3e5, 3e6])[rng.integers(0, 3, (400, 600))]
    estimate = estimate_noise(bracket(rate, rng), EXPOSURES, 64, white_level=4095)
    assert estimate.gain_e_per_dn == pytest.approx(GAIN, rel=0.01)
    assert estimate.read_noise_dn == pytest.approx(3.0 / GAIN, rel=0.03)


def test_noise_model_is_estimated_from_the_bracket_itself():
    rng = np.random.default_rng(6)
    rate = np.exp(rng.uniform(math.log(1e3), math.log(1e8), (300, 400)))
    estimate = estimate_noise(bracket(rate, rng), EXPOSURES, 64, white_level=4095)
    assert estimate.gain_e_per_dn == pytest.approx(GAIN, rel=0.03)
    assert estimate.read_noise_dn == pytest.approx(3.0 / GAIN, rel=0.15)
    assert estimate.source == "estimated"
    with pytest.raises(HDRError, match="not enough unsaturated signal"):
        estimate_noise(bracket(np.full((100, 100), 10.0), rng), EXPOSURES, 64, white_level=4095)


def test_superpixels_average_the_two_greens():
    mosaic = np.array([[1, 2], [4, 8]], dtype=np.float32)  # R G / G B
    np.testing.assert_allclose(superpixels(mosaic, "RGGB")[0, 0], [1, 3, 8])
    np.testing.assert_allclose(superpixels(mosaic, "BGGR")[0, 0], [8, 3, 1])


def test_debevec_recovers_radiance_from_8_bit_non_linear_brackets():
    rng = np.random.default_rng(7)
    radiance = np.exp(rng.uniform(math.log(0.05), math.log(200), (60, 80, 3))).astype(np.float32)
    times = np.array([1 / 400, 1 / 100, 1 / 25, 1 / 6], dtype=np.float32)
    images = [np.clip(255 * (radiance * t) ** (1 / 2.2), 0, 255).astype(np.uint8) for t in times]
    merged, response = merge_ldr(images, times)
    assert response.shape == (256, 1, 3)
    good = (radiance > 0.2) & (radiance < 50)
    correlation = np.corrcoef(np.log(merged[good]), np.log(radiance[good]))[0, 1]
    assert correlation > 0.99
    with pytest.raises(HDRError, match="needs 8-bit images"):
        merge_ldr([np.zeros((4, 4, 3), np.uint16)], [0.1])


def test_merge_dispatches_on_the_method_name():
    from processing.hdr.brackets import merge

    rng = np.random.default_rng(8)
    frames = bracket(np.full((6, 8), 1e6), rng)
    optimal = merge(frames, EXPOSURES, method="optimal", black_level=64, white_level=4095, noise=NOISE)
    poisson = merge(frames, EXPOSURES, method="poisson", black_level=64, white_level=4095, noise=NOISE)
    assert optimal.method == "optimal" and poisson.method == "poisson"
    np.testing.assert_allclose(poisson.radiance.mean(), 1e6 / GAIN, rtol=0.01)
    ldr = [np.full((8, 8, 3), v, np.uint8) for v in (20, 80, 200)]
    assert merge(ldr, [0.01, 0.04, 0.16], method="debevec").shape == (8, 8, 3)
    with pytest.raises(HDRError, match=r"method: 'median' is not one of \['debevec', 'optimal', 'poisson'\]"):
        merge(frames, EXPOSURES, method="median")


# --- the fast kernels against direct implementations ---------------------------------------------
def mirror_ball_bracket(rng, shape=(37, 51), exposures=EXPOSURES, sensor=SENSOR):
    """Mostly dark (read noise only), with lit patches from faint to saturated in every frame."""
    rate = np.full(shape, 50.0)
    lit = rng.random(shape) < 0.15
    rate[lit] = np.exp(rng.uniform(math.log(1e3), math.log(1e9), lit.sum()))
    rate[rng.random(shape) < 0.02] = 1e12
    return bracket(rate, rng, exposures=exposures, sensor=sensor)


def reference_merge(frames, exposures, black, threshold, noise, near_black_sigma=2.0, method="optimal"):
    """The estimator of the module's description, one pixel at a time (float64)."""
    exposures = np.asarray(exposures, float)
    read_var = noise.read_noise_dn**2 + 1 / 12
    inv_gain, near_black = 1 / noise.gain_e_per_dn, near_black_sigma * math.sqrt(read_var)
    k, h, w = frames.shape
    radiance, variance = np.empty((h, w)), np.empty((h, w))
    count, saturated = np.zeros((h, w), int), np.zeros((h, w), bool)
    index = np.arange(k)
    for y in range(h):
        for x in range(w):
            b, thr = black[y % 2, x % 2], threshold[y % 2, x % 2]
            v = frames[:, y, x].astype(float)
            ok = v < thr
            if not ok.any():
                j = np.argmin(exposures)
                radiance[y, x], variance[y, x], saturated[y, x] = (v[j] - b) / exposures[j], np.inf, True
                continue
            sum_y, sum_t = (v[ok] - b).sum(), exposures[ok].sum()
            x0 = max(sum_y / sum_t, 0.0)
            if method == "poisson":
                radiance[y, x] = sum_y / sum_t
                variance[y, x] = (x0 * sum_t * inv_gain + ok.sum() * read_var) / sum_t**2
                count[y, x] = ok.sum()
                continue
            mu = exposures * x0
            var = mu * inv_gain + read_var
            clear = ok & (mu + 3 * np.sqrt(var) < thr - b)
            if clear.any():
                longest = index[clear & (exposures == exposures[clear].max())][0]
                use = clear & ((mu >= near_black) | (index == longest))
                wgt = np.where(use, exposures**2 / var, 0.0)
                radiance[y, x] = (wgt * (v - b) / exposures).sum() / wgt.sum()
                variance[y, x], count[y, x] = 1 / wgt.sum(), use.sum()
            else:
                j = index[ok & (exposures == exposures[ok].min())][0]
                radiance[y, x] = (v[j] - b) / exposures[j]
                variance[y, x], count[y, x] = var[j] / exposures[j] ** 2, 1
    return radiance, variance, count, saturated


# Shuffled, with equal exposures; an odd size; fractional black levels per site.
AWKWARD = np.array([1.6e-3, 1e-4, 2.56e-2, 1.6e-3, 4e-4, 2.56e-2])
AWKWARD_BLACK = np.array([[63.7, 64.2], [64.0, 65.1]])


@pytest.mark.parametrize(
    ("exposures", "black", "near_black_sigma", "method"),
    [
        (EXPOSURES, 64, 2.0, "optimal"),
        (AWKWARD, AWKWARD_BLACK, 2.0, "optimal"),
        (AWKWARD, AWKWARD_BLACK, 0.0, "optimal"),
        (AWKWARD[:2], 64, 2.0, "optimal"),
        (AWKWARD[2:3], 64, 2.0, "optimal"),
        (AWKWARD, AWKWARD_BLACK, 2.0, "poisson"),
    ],
)
def test_merge_matches_a_per_pixel_reference(exposures, black, near_black_sigma, method):
    rng = np.random.default_rng(11)
    frames = mirror_ball_bracket(rng, exposures=exposures)
    frames[0, 0, :6] = [0, 4095, 4054, 4053, 64, 65]  # below black, clipped, at the threshold and next to it
    if len(exposures) == 6:
        # Only the two 1.6 ms samples unsaturated, both too near clipping: the first is kept.
        frames[:, 0, 7] = [4000, 4095, 4095, 3990, 4095, 4095]
    result = merge_raw(frames, exposures, black, 4095, NOISE, method=method, near_black_sigma=near_black_sigma)
    black_sites = np.broadcast_to(np.asarray(black, float), (2, 2))
    threshold = result.saturation_level - 0.01 * (result.saturation_level - black_sites)
    radiance, variance, count, saturated = reference_merge(
        frames, exposures, black_sites, threshold, NOISE, near_black_sigma, method
    )
    np.testing.assert_array_equal(result.count, count)
    np.testing.assert_array_equal(result.saturated, saturated)
    assert result.saturated.any() and (result.count >= (2 if len(exposures) > 2 else 1)).any()
    np.testing.assert_allclose(result.radiance, radiance, rtol=1e-6, atol=1e-3)
    np.testing.assert_allclose(result.variance, variance, rtol=1e-6)


@pytest.mark.parametrize("seed", [12, 13])
def test_dark_shortcut_agrees_with_the_general_path(seed):
    from processing.hdr.brackets import _run_merge

    rng = np.random.default_rng(seed)
    exposures = AWKWARD if seed % 2 else EXPOSURES
    # Several blocks per row and a partial one; big enough for the kernels to run in parallel.
    frames = mirror_ball_bracket(rng, shape=(97, 601), exposures=exposures)
    black = AWKWARD_BLACK if seed % 2 else np.full((2, 2), 64.0)
    threshold = np.full((2, 2), 4095.0) - 0.01 * (4095 - black)
    read_var = NOISE.read_noise_dn**2 + 1 / 12
    args = (frames, exposures, black, threshold, 1 / NOISE.gain_e_per_dn, read_var, 2 * math.sqrt(read_var), True)
    fast, general = _run_merge(*args), _run_merge(*args, shortcut=False)
    np.testing.assert_array_equal(fast[2], general[2])
    np.testing.assert_array_equal(fast[3], general[3])
    np.testing.assert_allclose(fast[0], general[0], rtol=1e-6)
    np.testing.assert_allclose(fast[1], general[1], rtol=1e-6)
    assert (fast[2] == 1).mean() > 0.5 and (fast[2] > 1).any()  # both paths taken


@pytest.mark.parametrize("shape", [(40, 60), (41, 63)])
def test_saturation_counts_match_a_direct_count(shape):
    from processing.hdr.brackets import _site_counts, _site_maxima

    rng = np.random.default_rng(14)
    clipped = SensorModel(20000, 3.0, 64, 3900, "RGGB")
    frames = mirror_ball_bracket(rng, shape=shape, sensor=clipped)
    site = frames[:, 1::2, 1::2]  # one site that never clips: its bright samples spread out
    frames[:, 1::2, 1::2] = np.where(site > 3000, rng.integers(1000, 3000, site.shape), site)
    top, rows = _site_maxima(frames)
    counts = _site_counts(frames, top, 4, rows)
    for sy in range(2):
        for sx in range(2):
            v = frames[:, sy::2, sx::2].astype(int)
            assert top[sy, sx] == v.max()
            assert counts[sy, sx, 0] == np.count_nonzero(v > v.max() - 4)
            assert counts[sy, sx, 1] == np.count_nonzero((v > v.max() - 164) & (v <= v.max() - 4))
    np.testing.assert_array_equal(measure_saturation(frames, 4095), [[3900, 3900], [3900, 4095]])


def reference_noise(frames, exposures, black, levels, bins=24):
    """Every usable pixel binned by its μ_a = r (y_a + y_b) / (1 + r), pairs whose expected
    y_b is within 85 % of the usable range only: the (x, y, weight) rows of estimate_noise's fit."""
    h, w = frames.shape[1:]
    black_map = np.tile(black, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    limit = np.tile(levels - 0.05 * (levels - black), ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    order = np.argsort(exposures)
    rows = []
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = exposures[a] / exposures[b]
        ya, yb = frames[a] - black_map, frames[b] - black_map
        usable = (frames[a] < limit) & (frames[b] < limit) & ((ya + yb) / (1 + r) < 0.85 * (limit - black_map))
        ya, yb = ya[usable], yb[usable]
        mu_a, d = r * (ya + yb) / (1 + r), ya - r * yb
        if mu_a.size < 1000 or mu_a.max() <= 20.0:
            continue
        edges = np.concatenate([[-np.inf, 20.0], np.geomspace(20.0, mu_a.max(), bins)[1:]])
        index = np.digitize(mu_a, edges[1:-1])
        for k in range(bins):
            sel = index == k
            if sel.sum() >= 100:
                rows.append([(1 + r) * mu_a[sel].mean(), 1 + r * r, d[sel].var() - (1 + r * r) / 12, sel.sum()])
    return np.array(rows)


@pytest.mark.parametrize(("exposures", "black"), [(EXPOSURES, np.full((2, 2), 64.0)), (AWKWARD, AWKWARD_BLACK)])
def test_noise_bins_match_binning_every_pixel(exposures, black):
    from processing.hdr.noise import _pair_bins

    rng = np.random.default_rng(15)
    rate = np.exp(rng.uniform(math.log(1e2), math.log(1e8), (301, 403)))
    rate[rng.random(rate.shape) < 0.5] = 50.0  # a dark background
    frames = bracket(rate, rng, exposures=exposures)
    levels = measure_saturation(frames, 4095)
    expected = reference_noise(frames, exposures, black, levels)
    got = []
    order = np.argsort(exposures)
    for a, b in zip(order[:-1], order[1:], strict=True):
        r = exposures[a] / exposures[b]
        binned = _pair_bins(frames, int(a), int(b), r, black, levels - 0.05 * (levels - black), 24)
        if binned is not None:
            got += [
                [(1 + r) * mu, 1 + r * r, var - (1 + r * r) / 12, n]
                for n, mu, var in zip(*binned, strict=True)
                if n >= 100
            ]
    got = np.array(got)
    assert got.shape == expected.shape and len(got) > 20
    np.testing.assert_array_equal(got[:, 3], expected[:, 3])
    np.testing.assert_allclose(got[:, :3], expected[:, :3], rtol=1e-9, atol=1e-12)
    estimate = estimate_noise(frames, exposures, black, white_level=4095)
    assert estimate.gain_e_per_dn == pytest.approx(GAIN, rel=0.05)


@pytest.mark.parametrize("cfa", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
def test_superpixels_match_the_tile_sums(cfa, dtype):
    rng = np.random.default_rng(16)
    mosaic = rng.uniform(0, 3000, (37, 52))
    if dtype != np.uint16:
        mosaic[rng.random(mosaic.shape) < 0.05] = np.nan
        mosaic[rng.random(mosaic.shape) < 0.05] = np.inf
        mosaic[0, :4] = [-0.0, 1e-45, 1e30, -1e30]
    mosaic = mosaic.astype(dtype)
    for view in (mosaic, mosaic[:, ::-1], mosaic[1:, 1:]):
        h, w = view.shape
        tiles = view[: h - h % 2, : w - w % 2].reshape(h // 2, 2, w // 2, 2).transpose(0, 2, 1, 3)
        expected = np.zeros((h // 2, w // 2, 3), np.float32)
        counts = np.zeros(3)
        for i, colour in enumerate(cfa):
            expected[..., "RGB".index(colour)] += tiles[..., i // 2, i % 2]
            counts["RGB".index(colour)] += 1
        with np.errstate(invalid="ignore"):
            expected /= counts.astype(np.float32)
        got = superpixels(view, cfa)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, expected)
        # Non-finite samples as 0 in the same pass: what the superpixels of the mosaic with
        # them set to 0 are, and every value finite.
        zeroed = superpixels(view, cfa, nonfinite=0.0)
        np.testing.assert_array_equal(zeroed, superpixels(np.where(np.isfinite(view), view, 0), cfa))
        assert np.isfinite(zeroed).all()
        if dtype != np.uint16:
            assert not np.isfinite(got).all()

"""The HDR merge against the noise model it assumes: bias, variance, and its edge cases.

Brackets come from the simulated sensor (Poisson shot noise, Gaussian read noise, 12-bit
quantisation, black level, clipping), with the radiance known exactly.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from processing.hdr import HDRError, NoiseModel, estimate_noise, measure_saturation, merge_ldr, merge_raw, superpixels
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
    from processing.hdr import merge

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

"""The auto bracket rule against its documented formulas."""

import math

import numpy as np
import pytest

from acquisition.daemon.bracketing import NoiseModel, electrons_for_snr, exposures_from_metering, is_saturated
from acquisition.daemon.settings import AutoBracketSettings
from drivers.camera import RawFrame

NOISE = NoiseModel(gain_e_per_dn=4.96, read_noise_e=3.0)


def frame(signal_dn, exposure_s, black=64, white=4095):
    mosaic = np.clip(np.rint(signal_dn + black), 0, white).astype(np.uint16)
    return RawFrame(mosaic, np.full((2, 2), float(black)), white, "RGGB", exposure_s, 0.0, "test")


def test_electrons_for_snr_solves_the_shot_plus_read_model():
    for snr in (5.0, 20.0, 100.0):
        e = electrons_for_snr(snr, 3.0)
        assert e / math.sqrt(e + 9.0) == pytest.approx(snr)


def test_bracket_spans_from_unsaturated_peak_to_the_target_snr_of_the_faintest_useful_pixel():
    rule = AutoBracketSettings()
    rng = np.random.default_rng(0)
    signal = rng.uniform(0, 50, (200, 300))
    signal[100, 150] = 2000.0  # the brightest useful pixel, at 2e6 DN/s
    signal[:2, :2] = 3000.0  # four hot pixels brighter still: past the fifth brightest
    meter = frame(signal, 0.001)
    exposures = exposures_from_metering(meter, rule, NOISE)
    rate = (meter.mosaic.astype(float) - 64) / 0.001
    peak = np.sort(rate.ravel())[-5]
    assert peak == pytest.approx(2e6, rel=0.02)
    assert exposures[0] == pytest.approx(rule.saturation_fraction * (4095 - 64) / peak)
    dark_e = rule.useful_fraction * peak * NOISE.gain_e_per_dn
    t_long = electrons_for_snr(rule.target_snr, NOISE.read_noise_e) / dark_e
    assert exposures[-1] == pytest.approx(t_long)
    ratios = np.array(exposures[1:]) / np.array(exposures[:-1])
    assert np.all(ratios <= rule.step_ratio + 1e-9) and len(exposures) <= rule.max_exposures


def test_count_is_capped_and_empty_scenes_and_saturation_are_handled():
    rule = AutoBracketSettings(max_exposures=3, useful_fraction=1e-6)
    signal = np.zeros((64, 64))
    signal[9:12, 9:12] = 3000.0  # a lit spot (a lone bright pixel is taken for a hot one)
    assert len(exposures_from_metering(frame(signal, 0.001), rule, NOISE)) == 3
    assert exposures_from_metering(frame(np.zeros((64, 64)), 0.001), rule, NOISE) == [rule.max_exposure_s]
    assert is_saturated(frame(np.full((8, 8), 5000.0), 0.001))
    assert not is_saturated(frame(np.full((8, 8), 1000.0), 0.001))

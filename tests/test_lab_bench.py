"""The lab benchmark's comparison of light models (the benchmark itself needs root and runs by
hand: `mirrorgonio bench lab`, docs/benchmarks.md)."""

import math

from acquisition.benchmarks.lab import SAME_RESULTS_RTOL, light_model_difference


def test_light_models_compare_number_by_number_and_anything_else_exactly():
    a = [{"name": "centre", "centre_m": [0.0, 0.001], "fit": {"peak": 2.0, "model": "gaussian"}}]
    assert light_model_difference(a, a) == 0.0
    b = [{"name": "centre", "centre_m": [0.0, 0.001 * (1 + 1e-12)], "fit": {"peak": 2.0, "model": "gaussian"}}]
    assert 0 < light_model_difference(a, b) < SAME_RESULTS_RTOL
    c = [{"name": "centre", "centre_m": [0.0, 0.001], "fit": {"peak": 2.002, "model": "gaussian"}}]
    assert math.isclose(light_model_difference(a, c), 0.002 / 2.002)
    for other in (
        [{"name": "+u", "centre_m": [0.0, 0.001], "fit": {"peak": 2.0, "model": "gaussian"}}],
        [{"name": "centre", "centre_m": [0.0], "fit": {"peak": 2.0, "model": "gaussian"}}],
        [{"name": "centre", "centre_m": [0.0, 0.001], "fit": {"peak": 2.0}}],
        [],
    ):
        assert light_model_difference(a, other) == math.inf
    assert light_model_difference([True], [1]) == math.inf  # a flag is not a number

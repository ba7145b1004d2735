"""Exposure brackets: a fixed list, or ``auto`` from a metering frame.

The ``auto`` rule (documented in ``docs/daemon.md``):

1. Meter at ``metering_exposure_s``; while the brightest pixel is saturated, meter again
   at an eighth of the time.
2. The brightest useful pixel is the :data:`PEAK_RANK`-th brightest of the black-subtracted
   signal rate (so a few hot pixels do not decide, while a pinhole's Fresnel peak, a few
   pixels across, does); the shortest exposure puts it at ``saturation_fraction`` of the
   sensor's range.
3. The darkest useful pixel is ``useful_fraction`` of that peak: fainter signal is
   treated as background. The longest exposure gives it ``target_snr`` under the
   shot-plus-read noise model (electrons ``e`` with ``e / sqrt(e + σ_read²) = SNR``).
4. Exposures between the two are spaced by at most ``step_ratio`` (2 stops by default),
   at most ``max_exposures`` of them, and clipped to the camera's range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from acquisition.daemon.models import AutoBracket
from acquisition.daemon.settings import AutoBracketSettings
from drivers.camera import RawFrame

#: The brightest pixel that meters the bracket is this one in order of brightness: hot
#: pixels come alone or in pairs, a lit spot covers tens of pixels.
PEAK_RANK = 5


@dataclass(frozen=True)
class NoiseModel:
    gain_e_per_dn: float
    read_noise_e: float


def auto_bracket_rule(defaults: AutoBracketSettings, bracket: AutoBracket) -> AutoBracketSettings:
    """The rule of a run's ``auto`` bracket: the daemon's ``defaults`` with the request's overrides."""
    return defaults.model_copy(update=bracket.overrides())


def electrons_for_snr(snr: float, read_noise_e: float) -> float:
    """Signal in electrons whose shot-plus-read SNR equals ``snr``."""
    return 0.5 * (snr * snr + snr * math.sqrt(snr * snr + 4.0 * read_noise_e**2))


def signal_rate(frame: RawFrame) -> np.ndarray:
    """Black-subtracted signal per second, DN/s, per photosite."""
    h, w = frame.mosaic.shape
    black = np.tile(frame.black_level, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    return (frame.mosaic.astype(np.float64) - black) / frame.exposure_s


def is_saturated(frame: RawFrame, fraction: float = 0.98) -> bool:
    top = frame.white_level - float(frame.black_level.max())
    return float(np.max(frame.mosaic.astype(np.float64) - frame.black_level.max())) >= fraction * top


def exposures_from_metering(frame: RawFrame, rule: AutoBracketSettings, noise: NoiseModel) -> list[float]:
    """The bracket for a scene metered by one unsaturated ``frame``."""
    rate = signal_rate(frame)
    flat = rate.ravel()
    peak = float(np.partition(flat, flat.size - PEAK_RANK)[flat.size - PEAK_RANK]) if flat.size >= PEAK_RANK else 0.0
    span = frame.white_level - float(frame.black_level.max())
    if peak <= 0.0:
        # Nothing above the noise: expose as long as allowed, one frame.
        return [rule.max_exposure_s]
    t_short = rule.saturation_fraction * span / peak
    dark_rate_e = rule.useful_fraction * peak * noise.gain_e_per_dn
    t_long = electrons_for_snr(rule.target_snr, noise.read_noise_e) / dark_rate_e
    t_short = min(max(t_short, rule.min_exposure_s), rule.max_exposure_s)
    t_long = min(max(t_long, t_short), rule.max_exposure_s)
    if t_long <= t_short * (1.0 + 1e-9):
        return [t_short]
    steps = math.ceil(math.log(t_long / t_short) / math.log(rule.step_ratio))
    count = min(steps + 1, rule.max_exposures)
    return [float(t) for t in np.geomspace(t_short, t_long, count)]

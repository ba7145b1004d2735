"""What a merge produces and assumes: the noise model, the merged position, the merge's errors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


class HDRError(ValueError):
    """A bracket that cannot be merged (one line naming the cause)."""


@dataclass(frozen=True)
class NoiseModel:
    """Photon-shot-plus-read noise of a sensor, in digital numbers."""

    gain_e_per_dn: float
    read_noise_dn: float
    source: str = "rig"  # where the figures came from: "rig" or "estimated"

    def variance(self, mean_dn: ArrayLike) -> np.ndarray:
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

"""The simulated sensor: photons to digital numbers on a Bayer mosaic.

Photon shot noise (Poisson in electrons), a full well that clips, Gaussian read noise,
a gain that maps the full well onto the white level, the black level offset, rounding
to integers and clipping to the ADC's range: the noise model the HDR merge assumes.
"""

from __future__ import annotations

import numpy as np

from drivers.contracts.rig import Camera as CameraSpec

CHANNEL_INDEX = {"R": 0, "G": 1, "B": 2}


def cfa_channels(pattern: str, height: int, width: int) -> np.ndarray:
    """Channel index (0 = R, 1 = G, 2 = B) of every photosite for a 2x2 CFA pattern."""
    tile = np.array(
        [[CHANNEL_INDEX[pattern[0]], CHANNEL_INDEX[pattern[1]]], [CHANNEL_INDEX[pattern[2]], CHANNEL_INDEX[pattern[3]]]]
    )
    return np.tile(tile, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def mosaic_of(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """Pick each photosite's own channel from a (3, H, W) image."""
    _, h, w = rgb.shape
    channels = cfa_channels(pattern, h, w)
    return np.take_along_axis(rgb, channels[None], axis=0)[0]


class SensorModel:
    """Expose a rate image and read it out as raw DN.

    Parameters
    ----------
    full_well_e, read_noise_e : float
        Capacity of a photosite and the read noise, in electrons.
    black_level_dn, white_level_dn : int
        The ADC's offset and its highest code.
    cfa_pattern : str
        e.g. ``"RGGB"``.
    noise : bool
        False gives the expected value, rounded: for analytic checks.
    """

    def __init__(
        self,
        full_well_e: float,
        read_noise_e: float,
        black_level_dn: int,
        white_level_dn: int,
        cfa_pattern: str,
        noise: bool = True,
    ):
        self.full_well_e = full_well_e
        self.read_noise_e = read_noise_e
        self.black_level_dn = black_level_dn
        self.white_level_dn = white_level_dn
        self.cfa_pattern = cfa_pattern
        self.noise = noise

    @classmethod
    def from_rig(cls, camera: CameraSpec, noise: bool = True) -> SensorModel:
        return cls(
            camera.full_well_e,
            camera.read_noise_e,
            camera.black_level_dn,
            camera.white_level,
            camera.cfa_pattern,
            noise,
        )

    @property
    def gain_e_per_dn(self) -> float:
        return self.full_well_e / (self.white_level_dn - self.black_level_dn)

    def expected_dn(self, electrons: np.ndarray) -> np.ndarray:
        """Mean signal above black in DN for a mean of ``electrons`` (before clipping)."""
        return np.asarray(electrons) / self.gain_e_per_dn

    def expose(self, rate_rgb: np.ndarray, exposure_s: float, rng: np.random.Generator) -> np.ndarray:
        """Raw mosaic (uint16) of an exposure of ``exposure_s`` to ``rate_rgb`` (e⁻/s)."""
        electrons = mosaic_of(rate_rgb, self.cfa_pattern) * exposure_s
        if self.noise:
            electrons = rng.poisson(np.minimum(electrons, 1e12)).astype(np.float64)
        electrons = np.minimum(electrons, self.full_well_e)
        if self.noise and self.read_noise_e > 0:
            electrons += rng.normal(0.0, self.read_noise_e, electrons.shape)
        dn = np.rint(electrons / self.gain_e_per_dn + self.black_level_dn)
        return np.clip(dn, 0, self.white_level_dn).astype(np.uint16)

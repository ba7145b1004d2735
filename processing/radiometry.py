"""From merged DN/s to electrons per second: the camera's gain and noise, and the usable pixels."""

from __future__ import annotations

import logging
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike

from drivers.contracts.runfile import RunFile
from processing.hdr.model import NoiseModel

log = logging.getLogger("mirrorgonio.processing")


def rig_noise(run: RunFile) -> NoiseModel:
    cam = run.header.rig.camera
    return NoiseModel(cam.gain_e_per_dn, cam.read_noise_e / cam.gain_e_per_dn, source="rig")


def radiometric_gain(run: RunFile) -> float:
    """e⁻ per DN for turning merged DN/s into e⁻/s: the rig's calibrated gain, always.

    The camera's sensitivity (e⁻/s per unit radiance) that the templates and cell sums
    divide by was calibrated with this gain, and the reflectance step converts with it too
    (``processing.reflectance``). A gain estimated from the brackets only weights the merge
    (the noise model): converting with it instead would scale the light's intensities,
    and so every albedo measured under it, by estimated/rig (+2.1 % on the bench's run).
    """
    return float(run.header.rig.camera.gain_e_per_dn)


#: How far an estimated gain may lie from the rig's before it is worth a warning: the
#: estimate from the brackets came out 2.1 % above the simulated camera's true gain on the
#: bench's run, and it only weights the merge; beyond this, the rig's figure is suspect.
GAIN_MISMATCH_WARNING = 0.05


def gain_mismatch(noise: NoiseModel, rig_gain: float) -> tuple[int, str] | None:
    """How far the noise model's gain lies from the rig's calibrated gain, as a logging level
    and one line: None within 1 %, a warning beyond :data:`GAIN_MISMATCH_WARNING`, else
    information. The light and the reflectance steps both say it so.

    Examples
    --------
    >>> gain_mismatch(NoiseModel(5.02, 0.6, source="estimated"), 5.0) is None
    True
    >>> level, line = gain_mismatch(NoiseModel(5.5, 0.6, source="estimated"), 5.0)
    >>> level == logging.WARNING, "+10.0 %" in line
    (True, True)
    """
    off = noise.gain_e_per_dn / rig_gain - 1.0
    if abs(off) <= 0.01:
        return None
    warn = abs(off) > GAIN_MISMATCH_WARNING
    advice = "; check the camera's calibration" if warn else ""
    return (
        logging.WARNING if warn else logging.INFO,
        f"the noise model's gain ({noise.source}, {noise.gain_e_per_dn:.4g} e-/DN) differs from the rig's calibrated "
        f"gain ({rig_gain:.4g} e-/DN) by {100 * off:+.1f} %: the merge is weighted with it, intensities use the "
        f"rig's{advice}",
    )


class ElectronRates:
    """A merged mosaic in DN/s (or DN²/s²) read as e⁻/s (or (e⁻/s)²): converted to float64
    and multiplied by each factor in turn only where it is indexed.

    The source estimates read a window around the templates and a few hundred pixels of
    the cells, out of 2.6 M; converting whole frames cost more (21 ms a position) than the
    estimates themselves. Any index gives the numbers ``array.astype(float64) * f1 * f2``
    would hold there.
    """

    __slots__ = ("dn", "factors", "shape")

    def __init__(self, dn: np.ndarray, *factors: float) -> None:
        self.dn, self.factors, self.shape = dn, factors, dn.shape

    def __getitem__(self, key: Any) -> np.ndarray:
        out = np.asarray(self.dn[key], dtype=np.float64)
        for factor in self.factors:
            out = out * factor
        return out


@numba.njit(cache=True)
def position_masks(radiance, variance, count, saturated):
    """One pass over a merged position: the usable pixels (a finite estimate from at least
    one unsaturated sample), the lit ones among them (3 σ above zero, in float32 as the
    arrays hold it) and the number saturated in every frame."""
    usable = np.empty(radiance.shape, np.bool_)
    lit = np.empty(radiance.shape, np.bool_)
    n_saturated = 0
    three = np.float32(3.0)
    largest = np.float32(3.4028234663852886e38)  # |x| <= largest: finite (nan compares false)
    r, v, c, s = radiance.ravel(), variance.ravel(), count.ravel(), saturated.ravel()
    u, li = usable.ravel(), lit.ravel()
    # Without branches (& rather than `and`), so that the loop vectorises.
    for i in range(r.size):
        n_saturated += np.int64(s[i])
        x = r[i]
        ok = (not s[i]) & (c[i] > 0) & (abs(x) <= largest)
        u[i] = ok
        li[i] = ok & (x > three * np.sqrt(v[i]))
    return usable, lit, n_saturated


def electron_rates(
    radiance: np.ndarray, variance: np.ndarray, count: np.ndarray, saturated: ArrayLike, gain: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Electron rates, their variance and the usable pixels of one merged position."""
    usable, _, _ = position_masks(radiance, variance, count, np.asarray(saturated, bool))
    return ElectronRates(radiance, gain)[...], ElectronRates(variance, gain, gain)[...], usable

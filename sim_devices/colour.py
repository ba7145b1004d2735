"""The simulated camera's colour: its channels' spectral sensitivities, the camera RGB of a
spectrum, and the DNG colour matrices derived from them against the CIE 1931 observer.

The simulation renders three channels; a truth emitter's ``spectrum`` is its camera RGB
relative to an equal-energy spectrum (each channel's sensitivity has unit area, so a flat
spectrum gives ``(1, 1, 1)``). The camera's sensitivities are the rig's Gaussian bands
(``channel_wavelengths_m``, ``channel_bandwidths_m``) or its tabulated
``[camera.spectral_response]``.

The colour matrices are made as a camera maker makes them (the DNG specification's
ColorMatrix, XYZ → camera): for each calibration illuminant (CIE A and D65) the 24 patches
of the ColorChecker (colour-science's ``BabelColor Average``) lit by it and the illuminant
itself are seen by the camera and by the CIE 1931 2° observer; the 3×3 matrix from camera
RGB to XYZ is the least-squares fit over the patches that maps the illuminant's white
exactly (white-point preserving), and the ColorMatrix is its inverse, scaled so that the
illuminant's white (Y = 1) gives a largest camera channel of 1. A camera whose channels
are not linear combinations of the observer's (any real one, and the Gaussian bands) is
then only approximately colorimetric: the fit's error is largest for narrow-band light.
"""

from __future__ import annotations

import copy
import math
from functools import lru_cache
from typing import Any

import numpy as np

from drivers.contracts.rig import Camera

#: Wavelengths of the colour computations, nanometres (CIE 1931 tables are 1 nm from 360).
WAVELENGTHS_NM = np.arange(360.0, 831.0, 1.0)
#: The DNG CalibrationIlluminant codes of the two matrices (EXIF LightSource: 17 StdA, 21 D65).
CALIBRATION_ILLUMINANTS = {"A": 17, "D65": 21}
#: The narrowest band a colour computation takes a channel as (FWHM, m): a rig may ask for a
#: single wavelength (bandwidth 0) for its point spread, which has no colour matrix.
MIN_COLOUR_BAND_M = 5e-9
_OBSERVER = "CIE 1931 2 Degree Standard Observer"
_C2_M_K = 1.438776877e-2  # the second radiation constant hc/k, m·K


def channel_sensitivities(camera: Camera) -> np.ndarray:
    """The camera's three channel sensitivities on :data:`WAVELENGTHS_NM`, (n, 3), each of unit
    area (per nm): so that a flat spectrum's camera RGB is ``(1, 1, 1)``.

    Parameters
    ----------
    camera : drivers.contracts.rig.Camera
        Its ``spectral_response`` when given (linear between the tabulated wavelengths, zero
        outside), else Gaussian bands of FWHM ``channel_bandwidths_m`` (at least
        :data:`MIN_COLOUR_BAND_M`) about ``channel_wavelengths_m``.
    """
    lam = WAVELENGTHS_NM * 1e-9
    curves = np.zeros((lam.size, 3))
    for c in range(3):
        if camera.spectral_response is not None:
            grid, response = camera.spectral_response.curve(c)
            curves[:, c] = np.interp(lam, grid, response, left=0.0, right=0.0)
        else:
            fwhm = max(camera.channel_bandwidths_m[c], MIN_COLOUR_BAND_M)
            sigma = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
            curves[:, c] = np.exp(-0.5 * ((lam - camera.channel_wavelengths_m[c]) / sigma) ** 2)
        area = curves[:, c].sum()
        if not area > 0:
            raise ValueError(f"camera channel {'RGB'[c]} does not respond within 360-830 nm")
        curves[:, c] /= area
    return curves


def planck(cct_k: float) -> np.ndarray:
    """A blackbody's relative spectral radiance at ``cct_k`` kelvin on :data:`WAVELENGTHS_NM`
    (peak 1)."""
    lam = WAVELENGTHS_NM * 1e-9
    radiance = lam**-5 / np.expm1(_C2_M_K / (lam * cct_k))
    return radiance / radiance.max()


def camera_rgb(spectrum: np.ndarray, camera: Camera) -> np.ndarray:
    """The camera RGB of a spectrum sampled on :data:`WAVELENGTHS_NM`: ``∫ S(λ) c_i(λ) dλ``
    for the channels of :func:`channel_sensitivities`."""
    return np.asarray(spectrum, dtype=float) @ channel_sensitivities(camera)


def blackbody_rgb(cct_k: float, camera: Camera) -> tuple[float, float, float]:
    """A blackbody emitter's ``spectrum`` weights (camera RGB, mean 1) at ``cct_k`` kelvin."""
    rgb = camera_rgb(planck(cct_k), camera)
    red, green, blue = rgb / rgb.mean()
    return float(red), float(green), float(blue)


def spectrum_xyz(spectrum: np.ndarray) -> np.ndarray:
    """CIE 1931 XYZ of a spectrum sampled on :data:`WAVELENGTHS_NM` (unnormalised sums)."""
    return np.asarray(spectrum, dtype=float) @ _cmfs()


@lru_cache(maxsize=1)
def _cmfs() -> np.ndarray:
    import colour  # noqa: PLC0415 - heavy (about a second): only the colour computations need it

    cmfs = colour.MSDS_CMFS[_OBSERVER].copy().align(colour.SpectralShape(360, 830, 1))
    return np.asarray(cmfs.values, dtype=float)


#: The maximum luminous efficacy of photopic vision (lm/W) with the CIE 1931 ȳ(λ) as V(λ).
K_M_LM_PER_W = 683.002


def candela_per_unit(cct_k: float, camera: Camera) -> float:
    """The luminous intensity (cd) of one unit of a blackbody emitter's intensity.

    The simulation's unit of intensity is the spectral radiant intensity seen through the
    camera's channels: an emitter of intensity ``I`` and relative spectrum ``S(λ)`` emits
    ``I · S(λ) / m`` W sr⁻¹ nm⁻¹, ``m`` the mean over the channels of ``∫ S c_i dλ`` (each
    ``c_i`` of unit area, :func:`channel_sensitivities`), so that its camera RGB has mean
    ``I``. Its luminous intensity is then ``K_m ∫ V(λ) I S(λ) / m dλ`` (CIE 1931 ȳ as V).

    Parameters
    ----------
    cct_k : float
        The blackbody's temperature, kelvin.
    camera : drivers.contracts.rig.Camera
        Whose channels define the unit.

    Examples
    --------
    >>> from drivers.contracts.rig import Camera
    >>> round(candela_per_unit(2856.0, Camera()), 1)
    83378.0
    """
    spectrum = planck(cct_k)
    spectrum = spectrum / float(np.mean(camera_rgb(spectrum, camera)))
    return K_M_LM_PER_W * float(spectrum @ _cmfs()[:, 1])  # 1 nm steps


@lru_cache(maxsize=1)
def _training() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The ColorChecker's reflectances (24, n) and each calibration illuminant's spectrum (n,)."""
    import colour  # noqa: PLC0415 - heavy

    shape = colour.SpectralShape(360, 830, 1)
    patches = colour.characterisation.SDS_COLOURCHECKERS["BabelColor Average"]
    # The patches are tabulated 380-780 nm: held at their end values beyond, as the CIE extrapolates.
    reflectances = np.array([sd.copy().align(shape).values for sd in patches.values()])
    illuminants = {name: colour.SDS_ILLUMINANTS[name].copy().align(shape).values for name in CALIBRATION_ILLUMINANTS}
    return {name: (reflectances, np.asarray(spd, dtype=float)) for name, spd in illuminants.items()}


def _camera_to_xyz(camera: Camera, illuminant: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The white-preserving least-squares camera RGB → XYZ matrix under ``illuminant``, with the
    illuminant's camera RGB and XYZ."""
    reflectances, spd = _training()[illuminant]
    sens, cmfs = channel_sensitivities(camera), _cmfs()
    lit = reflectances * spd[None, :]
    rgb, xyz = lit @ sens, lit @ cmfs  # (24, 3) each
    rgb_w, xyz_w = spd @ sens, spd @ cmfs
    # min ||M rgb - xyz||² subject to M rgb_w = xyz_w: the free fit corrected along (RᵀR)⁻¹ rgb_w.
    gram_inv = np.linalg.inv(rgb.T @ rgb)
    free = np.linalg.lstsq(rgb, xyz, rcond=None)[0].T  # (3, 3): xyz ≈ free @ rgb
    direction = gram_inv @ rgb_w
    matrix = free + np.outer(xyz_w - free @ rgb_w, direction) / (rgb_w @ direction)
    return matrix, rgb_w, xyz_w


def colour_matrices(camera: Camera) -> dict[str, Any]:
    """:func:`derive_colour_matrices`, once per process and set of channel sensitivities."""
    response = camera.spectral_response.model_dump_json() if camera.spectral_response is not None else ""
    key = (tuple(camera.channel_wavelengths_m), tuple(camera.channel_bandwidths_m), response)
    return copy.deepcopy(_colour_matrices(key, camera))


_CACHE: dict[tuple, dict[str, Any]] = {}


def _colour_matrices(key: tuple, camera: Camera) -> dict[str, Any]:
    if key not in _CACHE:
        _CACHE[key] = derive_colour_matrices(camera)
    return _CACHE[key]


def derive_colour_matrices(camera: Camera) -> dict[str, Any]:
    """The DNG colour description of the simulated camera (``docs/run-file.md``, "Camera colour").

    Returns
    -------
    dict
        ``color_matrix_1`` and ``color_matrix_2`` (XYZ → camera, row-major 3×3, for the
        ``calibration_illuminant_1`` CIE A and ``calibration_illuminant_2`` D65, each scaled so
        that its illuminant's white of Y = 1 has a largest channel of 1) and
        ``as_shot_neutral`` (the camera RGB of D65, largest channel 1), and ``source``.
    """
    out: dict[str, Any] = {"source": "simulated camera: its channels against the CIE 1931 observer"}
    for k, name in enumerate(CALIBRATION_ILLUMINANTS, start=1):
        to_xyz, _, xyz_w = _camera_to_xyz(camera, name)
        color_matrix = np.linalg.inv(to_xyz)
        color_matrix /= (color_matrix @ (xyz_w / xyz_w[1])).max()
        out[f"color_matrix_{k}"] = [[float(v) for v in row] for row in color_matrix]
        out[f"calibration_illuminant_{k}"] = CALIBRATION_ILLUMINANTS[name]
    _, rgb_d65, _ = _camera_to_xyz(camera, "D65")
    out["as_shot_neutral"] = [float(v) for v in rgb_d65 / rgb_d65.max()]
    return out

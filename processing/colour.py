"""Colour of the measured light: camera RGB → CIE XYZ through the camera's colour matrices,
then chromaticity (x, y; u', v'), correlated colour temperature and Duv (colour-science).

The matrices are the ones the run's raw files carry (:mod:`drivers.contracts.camera_colour`):
the DNG ColorMatrix maps XYZ to camera RGB under its calibration illuminant. With two of
them the matrix for a light is interpolated between the two in inverse CCT, as the DNG
specification does for a white balance: start from the second matrix, take the XYZ it gives,
its CCT, weigh ``(1/T − 1/T₂) / (1/T₁ − 1/T₂)`` (clipped to [0, 1]) of the first matrix, and
repeat until the CCT settles. The light's camera RGB is then ``inverse(ColorMatrix) · RGB``
up to scale, which is all chromaticity needs.

CCT and Duv are Ohno's (2013) from the CIE 1960 (u, v) of the chromaticity; a light farther
than 0.05 in Duv from the Planckian locus has no CCT (CIE 015), so none is given. Without
matrices (a camera whose files carry none, a run file from before the run file kept them)
the colour is camera RGB only, and every section says so.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from drivers.contracts.camera_colour import ILLUMINANT_CCT_K
from drivers.contracts.rig import Camera

__all__ = [
    "DUV_LIMIT",
    "binned_colour",
    "camera_to_xyz",
    "chromaticity",
    "colour_section",
    "describe",
    "luminance_over_reference",
    "over_theta",
    "planckian_luminance_ratios",
    "relative_luminance",
]

#: The largest |Duv| a CCT is given for (CIE 015:2018).
DUV_LIMIT = 0.05
#: Degrees of θ a colour-over-angle bin spans.
THETA_BIN_DEG = 5.0
#: The largest distance in u'v' between the bins' colours for which a colour is taken as one
#: for all angles (a just noticeable difference is about 0.001–0.004).
VARIES_UV = 0.002
#: The weakest bin, as a fraction of the strongest bin's signal, that the judgement of
#: whether a colour varies takes: the weak bins far out in a lobe's tail are mostly noise and
#: the neighbours' light (they are kept in the record all the same).
JUDGED_SIGNAL = 0.1


def _interpolated_matrix(description: dict[str, Any], cct_k: float) -> np.ndarray:
    """The XYZ → camera matrix for a light of ``cct_k``: the two matrices weighed in 1/T."""
    first = np.asarray(description["color_matrix_1"], dtype=float)
    if "color_matrix_2" not in description:
        return first
    second = np.asarray(description["color_matrix_2"], dtype=float)
    t1 = ILLUMINANT_CCT_K[description["calibration_illuminant_1"]]
    t2 = ILLUMINANT_CCT_K[description["calibration_illuminant_2"]]
    if t1 == t2:
        return first
    weight = (1.0 / cct_k - 1.0 / t2) / (1.0 / t1 - 1.0 / t2) if math.isfinite(cct_k) and cct_k > 0 else 0.0
    weight = min(max(weight, 0.0), 1.0)
    return weight * first + (1.0 - weight) * second


def camera_to_xyz(rgb: Sequence[float] | np.ndarray, description: dict[str, Any]) -> np.ndarray:
    """CIE 1931 XYZ (Y = 1) of a light whose camera RGB is ``rgb``, through the camera's colour
    matrices ``description`` (interpolated in inverse CCT where there are two).

    Parameters
    ----------
    rgb : array_like, shape (3,)
        The camera's raw channels (black subtracted), any scale.
    description : dict
        The run file's camera colour (:mod:`drivers.contracts.camera_colour`).

    Returns
    -------
    ndarray, shape (3,)
        XYZ scaled to Y = 1 (NaN where the light has no positive luminance).
    """
    rgb = np.asarray(rgb, dtype=float).reshape(3)
    cct = math.nan
    xyz = np.full(3, np.nan)
    for _ in range(20):
        xyz = np.linalg.solve(_interpolated_matrix(description, cct), rgb)
        if not xyz[1] > 0:
            return np.full(3, np.nan)
        new = _cct_duv(xyz)[0]
        if not math.isfinite(new) or (math.isfinite(cct) and abs(new - cct) < 0.01):
            break
        cct = new
    return xyz / xyz[1]


def _cct_duv(xyz: np.ndarray) -> tuple[float, float]:
    import colour  # noqa: PLC0415 - colour-science takes a second to import

    total = float(np.sum(xyz))
    if not total > 0:
        return math.nan, math.nan
    uv = colour.xy_to_UCS_uv(np.asarray(xyz[:2]) / total)
    cct, duv = (float(v) for v in colour.temperature.uv_to_CCT(uv, method="Ohno 2013"))
    return cct, duv


def chromaticity(xyz: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """The chromaticity of an XYZ: ``x``, ``y`` (CIE 1931), ``u_prime``, ``v_prime`` (CIE 1976
    UCS), ``cct_k`` and ``duv`` (Ohno 2013; ``cct_k`` None where |Duv| > :data:`DUV_LIMIT`).

    Examples
    --------
    >>> c = chromaticity([0.95047, 1.0, 1.08883])  # D65's white
    >>> round(c["x"], 4), round(c["y"], 4), round(c["cct_k"], -1)
    (0.3127, 0.329, 6500.0)
    """
    import colour  # noqa: PLC0415 - heavy

    xyz = np.asarray(xyz, dtype=float).reshape(3)
    total = float(xyz.sum())
    if not (np.all(np.isfinite(xyz)) and total > 0):
        return {"x": None, "y": None, "u_prime": None, "v_prime": None, "cct_k": None, "duv": None}
    x, y = xyz[:2] / total
    u_prime, v_prime = (float(v) for v in colour.xy_to_Luv_uv(np.array([x, y])))
    cct, duv = _cct_duv(xyz)
    return {
        "x": float(x),
        "y": float(y),
        "u_prime": u_prime,
        "v_prime": v_prime,
        "cct_k": cct if abs(duv) <= DUV_LIMIT and math.isfinite(cct) else None,
        "duv": duv if math.isfinite(duv) else None,
    }


def _basis(description: dict[str, Any]) -> str:
    if not description:
        return "camera RGB only: the run file holds no colour matrices for its camera"
    source = description.get("source") or "the raw files"
    return f"CIE 1931 2° XYZ from camera RGB through the camera's colour matrices ({source})"


def colour_section(rgb: Sequence[float] | np.ndarray, description: dict[str, Any]) -> dict[str, Any]:
    """The colour record of a light of camera RGB ``rgb``: ``basis`` (what the numbers are), the
    ``camera_rgb`` (mean 1) and, with matrices, ``XYZ`` (Y = 1) and its :func:`chromaticity`."""
    rgb = np.asarray(rgb, dtype=float).reshape(3)
    section: dict[str, Any] = {"basis": _basis(description), "camera_rgb": [float(v) for v in rgb / rgb.mean()]}
    if description and np.all(np.isfinite(rgb)) and rgb.sum() > 0:
        xyz = camera_to_xyz(rgb, description)
        section["XYZ"] = [float(v) for v in xyz]
        section.update(chromaticity(xyz))
    return section


def over_theta(
    theta: np.ndarray, rgb: np.ndarray, description: dict[str, Any], bin_deg: float = THETA_BIN_DEG
) -> dict[str, Any]:
    """A light's colour over the zenith angle: its samples' camera RGB summed in bins of
    ``bin_deg`` of θ (so that the strong samples count most), each bin's chromaticity.

    Parameters
    ----------
    theta : ndarray, shape (n,)
        Each sample's θ, radians.
    rgb : ndarray, shape (n, 3)
        Each sample's intensity per camera channel (NaN where not measured).
    description : dict
        The camera's colour matrices (empty: camera RGB only).

    Returns
    -------
    dict
        ``theta_deg`` (the bins' mean θ, weighted as their colour), ``samples`` per bin,
        ``camera_rgb`` per bin and, with matrices, ``x``, ``y``, ``u_prime``, ``v_prime``,
        ``cct_k``, ``duv`` per bin, and ``max_delta_uv``: the largest u'v' distance from the
        light's mean colour of a bin with at least :data:`JUDGED_SIGNAL` of the strongest bin's
        signal; ``varies``: whether it exceeds :data:`VARIES_UV`.
    """
    theta = np.asarray(theta, dtype=float).reshape(-1)
    rgb = np.asarray(rgb, dtype=float).reshape(-1, 3)
    ok = np.isfinite(theta) & np.all(np.isfinite(rgb), axis=1) & (rgb.sum(axis=1) > 0)
    degrees = np.degrees(np.abs(theta[ok]))
    bins = np.floor(degrees / bin_deg).astype(int)
    centres, samples, totals = [], [], []
    for b in np.unique(bins):
        members = bins == b
        weight = rgb[ok][members].sum(axis=1)
        centres.append(float(np.sum(degrees[members] * weight) / weight.sum()))
        samples.append(int(members.sum()))
        totals.append(rgb[ok][members].sum(axis=0))
    out: dict[str, Any] = {"bin_deg": bin_deg}
    out.update(binned_colour(centres, np.reshape(totals, (-1, 3)), description))
    out["samples"] = samples
    return out


def binned_colour(theta_deg: Sequence[float], rgb: np.ndarray, description: dict[str, Any]) -> dict[str, Any]:
    """The colour record of bins of θ from each bin's camera RGB (summed, any scale): the fields
    of :func:`over_theta` but ``bin_deg`` and ``samples``; the light's mean colour, that
    ``max_delta_uv`` is measured from, is the bins' sum."""
    rgb = np.asarray(rgb, dtype=float).reshape(-1, 3)
    keys = ("x", "y", "u_prime", "v_prime", "cct_k", "duv")
    out: dict[str, Any] = {"theta_deg": [float(t) for t in theta_deg], "camera_rgb": []}
    if description:
        out.update({k: [] for k in keys})
    for total in rgb:
        out["camera_rgb"].append([float(v) for v in total / total.mean()])
        if description:
            c = chromaticity(camera_to_xyz(total, description))
            for k in keys:
                out[k].append(c[k])
    if description and out["u_prime"]:
        mean = chromaticity(camera_to_xyz(rgb.sum(axis=0), description))
        signal = rgb.sum(axis=1)
        distances = [
            math.hypot(u - mean["u_prime"], v - mean["v_prime"])
            for u, v, s in zip(out["u_prime"], out["v_prime"], signal, strict=True)
            if u is not None and v is not None and s >= JUDGED_SIGNAL * signal.max()
        ]
        out["max_delta_uv"] = max(distances, default=0.0)
        out["varies"] = bool(out["max_delta_uv"] > VARIES_UV)
    return out


def relative_luminance(
    rgb: Sequence[Sequence[float]] | np.ndarray, weights: Sequence[float] | np.ndarray, description: dict[str, Any]
) -> list[float]:
    """Each light's luminance Y per unit of camera signal (its channel mean), over their mean
    weighed by ``weights``, all through one matrix: the one for the lights mixed by ``weights``.

    A light model's intensity is the camera's channel mean; two sources of equal intensity and
    different colours differ in luminance. One matrix for all (the DNG matrices interpolated at
    the mix's CCT) keeps their scales comparable: the two calibration matrices are scaled
    apart. The weighed mean is 1, so the weights' total luminous share is unchanged.

    Parameters
    ----------
    rgb : array_like, shape (n, 3)
        Each light's camera RGB (any scale; each is taken at a channel mean of 1).
    weights : array_like, shape (n,)
        Each light's share of the mix (its flux).
    description : dict
        The camera's colour matrices (empty: all 1, the camera signal only).

    Returns
    -------
    list of float
    """
    channels, weights = _unit_channels(rgb), np.asarray(weights, dtype=float).reshape(-1)
    mixed = weights @ channels
    if not description or not (np.all(np.isfinite(mixed)) and mixed.sum() > 0):
        return [1.0] * len(channels)
    luminance = np.linalg.solve(_mix_matrix(mixed, description), channels.T)[1]
    mean = float(weights @ luminance) / float(weights.sum())
    if not (np.all(np.isfinite(luminance)) and mean > 0):
        return [1.0] * len(channels)
    return [float(v) for v in luminance / mean]


def _unit_channels(rgb: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """Camera RGB rows, (n, 3), each at a channel mean of 1."""
    channels = np.asarray(rgb, dtype=float).reshape(-1, 3)
    return channels / channels.mean(axis=1, keepdims=True)


def _mix_matrix(mixed: np.ndarray, description: dict[str, Any]) -> np.ndarray:
    """The one XYZ → camera matrix several lights are compared through: the matrices
    interpolated at their mix's CCT."""
    return _interpolated_matrix(description, _cct_duv(camera_to_xyz(mixed, description))[0])


def luminance_over_reference(
    rgb: Sequence[Sequence[float]] | np.ndarray,
    weights: Sequence[float] | np.ndarray,
    reference_rgb: Sequence[float] | np.ndarray,
    description: dict[str, Any],
) -> tuple[np.ndarray, np.ndarray]:
    """Each light's luminance per unit of camera signal over a reference light's: how a
    photometric scale measured on the reference carries over to lights of other colours.

    Through one matrix, the mix's (as :func:`relative_luminance`), so that the two calibration
    matrices' different scales cancel. The spectral mismatch of a three-channel camera (no
    3×3 matrix is exact for every spectrum) is estimated by the same ratio through each
    calibration matrix alone: half their difference, as a fraction.

    Parameters
    ----------
    rgb : array_like, shape (n, 3)
        Each light's camera RGB (any scale; each is taken at a channel mean of 1).
    weights : array_like, shape (n,)
        Each light's share of the mix (its flux).
    reference_rgb : array_like, shape (3,)
        The reference's camera RGB.
    description : dict
        The camera's colour matrices (empty: every ratio 1, the camera signal only).

    Returns
    -------
    ratios : ndarray (n,)
        Each light's luminance over the reference's, per unit of camera signal.
    mismatch : ndarray (n,)
        Each ratio's estimated spectral-mismatch error, a fraction (0 with one matrix).
    """
    channels, weights = _unit_channels(rgb), np.asarray(weights, dtype=float).reshape(-1)
    reference = _unit_channels(np.asarray(reference_rgb, dtype=float).reshape(1, 3))[0]
    if not description:
        return np.ones(len(channels)), np.zeros(len(channels))

    def ratios_through(matrix: np.ndarray) -> np.ndarray:
        luminance = np.linalg.solve(matrix, np.column_stack([channels.T, reference]))[1]
        return luminance[:-1] / luminance[-1]

    ratios = ratios_through(_mix_matrix(weights @ channels / weights.sum(), description))
    mismatch = np.zeros(len(channels))
    if "color_matrix_2" in description:
        first = ratios_through(np.asarray(description["color_matrix_1"], dtype=float))
        second = ratios_through(np.asarray(description["color_matrix_2"], dtype=float))
        mismatch = 0.5 * np.abs(first - second) / ratios
    return ratios, mismatch


#: The farthest a light may lie from the Planckian locus (Duv) for the spectral-mismatch
#: correction to take its spectrum as a blackbody's (about twice a white LED's usual spread).
PLANCKIAN_DUV = 0.006
_WAVELENGTHS_NM = np.arange(360.0, 831.0, 1.0)
_SECOND_RADIATION_M_K = 1.438776877e-2


def _channel_curves(camera: Camera) -> np.ndarray:
    """The described camera's three channel responses on 360-830 nm (1 nm), (n, 3), each of
    unit area: tabulated (linear, zero outside) or Gaussian bands of the stated FWHM."""
    lam = _WAVELENGTHS_NM * 1e-9
    curves = np.empty((lam.size, 3))
    for c in range(3):
        if camera.spectral_response is not None:
            grid, response = camera.spectral_response.curve(c)
            curves[:, c] = np.interp(lam, grid, response, left=0.0, right=0.0)
        else:
            fwhm = max(camera.channel_bandwidths_m[c], 1e-9)  # a single wavelength: the nearest nanometre
            width = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
            curves[:, c] = np.exp(-0.5 * ((lam - camera.channel_wavelengths_m[c]) / width) ** 2)
        curves[:, c] /= max(float(curves[:, c].sum()), 1e-300)
    return curves


def _luminance_per_signal(cct_k: float, curves: np.ndarray) -> float:
    """A blackbody's luminance (ȳ) per unit of the channels' mean response, any common scale."""
    lam = _WAVELENGTHS_NM * 1e-9
    spectrum = lam**-5 / np.expm1(_SECOND_RADIATION_M_K / (lam * cct_k))
    return float(spectrum @ _ybar()) / float(np.mean(spectrum @ curves))


@functools.lru_cache(maxsize=1)
def _ybar() -> np.ndarray:
    """The CIE 1931 2° observer's ȳ (V) on 360-830 nm, 1 nm."""
    import colour  # noqa: PLC0415 - colour-science takes a second to import

    observer = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy()
    return np.asarray(observer.align(colour.SpectralShape(360, 830, 1)).values, dtype=float)[:, 1]


def planckian_luminance_ratios(cct_k: Sequence[float | None], reference_cct_k: float, camera: Camera) -> np.ndarray:
    """Each light's luminance per unit of camera signal over the reference's, its spectrum taken
    as a blackbody's at its measured CCT: the spectral-mismatch correction of a photometer
    with a known spectral responsivity (CIE 198-SP1), with the camera's channels as the rig
    describes them. NaN where a light has no CCT.

    Examples
    --------
    >>> ratios = planckian_luminance_ratios([2856.0, 5000.0], 2856.0, Camera())
    >>> [round(float(r), 4) for r in ratios]
    [1.0, 0.9114]
    """
    curves = _channel_curves(camera)
    reference = _luminance_per_signal(reference_cct_k, curves)
    return np.array(
        [
            _luminance_per_signal(t, curves) / reference if t is not None and math.isfinite(t) else math.nan
            for t in cct_k
        ]
    )


def describe(section: dict[str, Any]) -> str:
    """A colour record in one line of ASCII, as the light files carry it: "x 0.4369, y 0.4041
    (CIE 1931 2 deg), u' 0.2560, v' 0.5242, CCT 3000 K, Duv +0.0000"; the camera RGB where the
    run had no colour matrices; "" for no record.

    Examples
    --------
    >>> describe({"camera_rgb": [1.2, 1.0, 0.8], "basis": "camera RGB only"})
    'camera RGB only (no colour matrices): R/G/B 1.200/1.000/0.800 of their mean'
    """
    if not section:
        return ""
    if section.get("x") is None:
        rgb = section.get("camera_rgb") or []
        return "camera RGB only (no colour matrices): R/G/B " + "/".join(f"{v:.3f}" for v in rgb) + " of their mean"
    cct = section.get("cct_k")
    return (
        f"x {section['x']:.4f}, y {section['y']:.4f} (CIE 1931 2 deg), u' {section['u_prime']:.4f}, "
        f"v' {section['v_prime']:.4f}, "
        + (f"CCT {cct:.0f} K" if cct is not None else "no CCT (|Duv| > 0.05)")
        + (f", Duv {section['duv']:+.4f}" if section.get("duv") is not None else "")
    )

"""An object's whole reflectance per point: diffuse albedo, specular reflectance and roughness.

Every usable (light, point) sample of an object run is a linear radiance ``L`` (R, G, B),
the irradiance ``E`` the light model gives there, the direction ``l`` towards the light and
``v`` towards the camera. The model fitted per point is a Lambertian part and a GGX
microfacet lobe with Smith's height-correlated masking–shadowing and Schlick's Fresnel::

    L_c = E_c · (ρ_c/π + K·(F0_c·(1 − w) + w)),   K = D(h)·G₂(l, v) / (4 (n·l)(n·v)),
    w = (1 − v·h)⁵

with ρ the diffuse albedo, F0 the specular reflectance at normal incidence and α the
roughness in D and G₂. Two materials are tried at every point and the better kept: a
*dielectric* (a body colour ρ under a coat whose reflection is grey, F0 from 0 to 0.1: about
0.04 for glazes, varnishes and lacquers) and a *metal* (no body colour, a tinted F0); the
point's metalness is which one won. For a fixed α either model is linear in its colours,
a small weighted least-squares problem per point; α is searched on a log grid and refined
by parabolas through the χ² minimum (the variable projection of Golub & Pereyra, 1973).
A grey coat is physics (a dielectric's Fresnel reflectance hardly depends on wavelength)
and it matters: with a free F0 per channel a broad, tinted lobe can pass for part of the
body colour.

Weights: a sample's variance is taken proportional to its radiance plus a floor (shot noise
dominates in an HDR merge), and the parameters' 1σ come from the least-squares covariance
scaled by the point's own residuals (χ² per degree of freedom when above 1), so a model that
does not fit a point widens its error bars instead of hiding.

A point whose samples never come near its mirror direction cannot pin its lobe: the χ²
hardly changes with α. Such points do not get an invented lobe: :func:`share_lobes`
clusters the points whose lobe is pinned into a few basis materials (k-means on the
diffuse chromaticity and brightness, the way Lensch et al. 2003 share basis BRDFs), gives
each unpinned point the lobe of the basis whose diffuse colour is nearest, refits its albedo
with that lobe, and marks it in the confidence map.

References: Walter et al., "Microfacet models for refraction through rough surfaces",
EGSR 2007; Heitz, "Understanding the masking-shadowing function", JCGT 3(2), 2014;
Lensch, Kautz, Goesele, Heidrich & Seidel, "Image-based reconstruction of spatial
appearance and geometric detail", ACM TOG 22(2), 2003.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numba
import numpy as np

from processing.parallel import default_workers, in_dask_worker

#: Roughness values searched (GGX α): from a polished lacquer to a nearly Lambertian lobe.
ROUGHNESS_GRID = np.geomspace(0.02, 1.0, 36)

#: A point's mirror direction is probed when a sample's half vector comes this close to its normal (degrees).
PROBE_DEG = 10.0

#: A point whose χ² per degree of freedom passes this many times the median point's is not explained.
OUTLIER_CHI2 = 4.0

#: Below this F0 (with 2σ) a point whose mirror direction was probed is matte: half a glaze's 0.04.
MATTE_F0 = 0.02

#: The index whose Fresnel curve shapes a dielectric coat's reflection against the angle.
COAT_IOR = 1.5

#: The largest F0 a dielectric is given: an index of 1.93 (glazes, varnishes, lacquers: 0.03-0.06).
DIELECTRIC_F0_MAX = 0.1

#: Basis colours closer than this (chromaticity, and a quarter of the log brightness) are one material.
SAME_COLOUR = 0.03

#: Confidence of a point's lobe.
CONFIDENCE_NONE, CONFIDENCE_SHARED, CONFIDENCE_OWN = 0, 1, 2


def ggx_lobe(cos_l: np.ndarray, cos_v: np.ndarray, cos_h: np.ndarray, alpha: float | np.ndarray) -> np.ndarray:
    """``K = D(h)·G₂(l, v) / (4 (n·l)(n·v))`` for GGX, height-correlated Smith; 0 below the surface.

    >>> round(float(ggx_lobe(np.array(1.0), np.array(1.0), np.array(1.0), 1.0)), 6)  # α = 1, normal
    0.079577
    """
    a2 = np.asarray(alpha, dtype=float) ** 2
    cl = np.clip(cos_l, 1e-6, 1.0)
    cv = np.clip(cos_v, 1e-6, 1.0)
    ch = np.clip(cos_h, 0.0, 1.0)
    d = a2 / (math.pi * (ch * ch * (a2 - 1.0) + 1.0) ** 2)
    lam_l = 0.5 * (np.sqrt(1.0 + a2 * (1.0 - cl * cl) / (cl * cl)) - 1.0)
    lam_v = 0.5 * (np.sqrt(1.0 + a2 * (1.0 - cv * cv) / (cv * cv)) - 1.0)
    g2 = 1.0 / (1.0 + lam_l + lam_v)
    return np.where((cos_l > 0) & (cos_v > 0) & (cos_h > 0), d * g2 / (4.0 * cl * cv), 0.0)


@dataclass
class Geometry:
    """The angles of every sample, (n_lights, N) each: ``n·l``, ``n·v``, ``n·h`` and ``v·h``."""

    cos_l: np.ndarray
    cos_v: np.ndarray
    cos_h: np.ndarray
    cos_vh: np.ndarray

    @classmethod
    def of(cls, light_dirs: np.ndarray, view: np.ndarray, normals: np.ndarray) -> Geometry:
        """From unit directions towards the lights (n_lights, N, 3), the camera (N, 3), the normals (N, 3)."""
        half = light_dirs + view[None]
        half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
        return cls(
            cos_l=np.einsum("jnk,nk->jn", light_dirs, normals),
            cos_v=np.broadcast_to(np.einsum("nk,nk->n", view, normals), light_dirs.shape[:2]),
            cos_h=np.einsum("jnk,nk->jn", half, normals),
            cos_vh=np.einsum("jnk,nk->jn", half, view),
        )


@dataclass
class BRDFFit:
    """The fitted reflectance of N points, with 1σ, the fit's quality and its confidence."""

    diffuse: np.ndarray  # (N, 3) ρ
    specular: np.ndarray  # (N, 3) F0
    roughness: np.ndarray  # (N,) α
    sigma_diffuse: np.ndarray  # (N, 3)
    sigma_specular: np.ndarray  # (N, 3)
    sigma_roughness: np.ndarray  # (N,)
    chi2: np.ndarray  # (N,) χ² per degree of freedom (weights up to a scale: its spread matters)
    samples: np.ndarray  # (N,) usable samples
    highlights: np.ndarray  # (N,) samples with the fitted lobe above a quarter of its peak
    confidence: np.ndarray  # (N,) CONFIDENCE_*
    metal: np.ndarray  # (N,) bool: the better material is a metal
    basis: list[dict] = field(default_factory=list)

    @property
    def metalness(self) -> np.ndarray:
        """1 for the points fitted as a metal (no body colour, a tinted F0), 0 for dielectrics."""
        return self.metal.astype(float)


def _solve_materials(
    cols: Columns, y: np.ndarray, wgt: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The better of two materials per point, for the columns (n_lights, N, 3) and weights.

    A dielectric: ``y_c ≈ ρ_c·diffuse_c + F0·coat_c`` with one, grey F0 in
    [0, :data:`DIELECTRIC_F0_MAX`] (a coat's reflection has no colour of its own) and
    ρ_c ≥ 0; a metal: ``y_c ≈ F0_c·metal_c + metal_offset_c`` with no body colour. Returns
    ρ (N, 3), F0 (N, 3), χ² (N,) and the metal flag (N,).
    """
    a, b = cols.diffuse, cols.coat
    saa = np.sum(wgt * a * a, axis=0)  # (N, 3)
    sbb = np.sum(wgt * b * b, axis=0)
    sab = np.sum(wgt * a * b, axis=0)
    say = np.sum(wgt * a * y, axis=0)
    sby = np.sum(wgt * b * y, axis=0)
    syy = np.sum(wgt * y * y, axis=0)
    ym = y - cols.metal_offset
    smm = np.sum(wgt * cols.metal * cols.metal, axis=0)
    smy = np.sum(wgt * cols.metal * ym, axis=0)
    symy = np.sum(wgt * ym * ym, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(saa > 0, sab / saa, 0.0)
        # The grey F0 by the Schur complement of the three diffuse unknowns.
        f0 = np.sum(sby - ratio * say, axis=1) / np.sum(sbb - ratio * sab, axis=1)
        f0 = np.clip(np.nan_to_num(f0, nan=0.0), 0.0, DIELECTRIC_F0_MAX)
        rho = np.maximum(np.where(saa > 0, (say - sab * f0[:, None]) / saa, 0.0), 0.0)
        metal_f0 = np.maximum(np.where(smm > 0, smy / smm, 0.0), 0.0)
    f0_rgb = np.repeat(f0[:, None], 3, axis=1)
    chi_d = syy - 2 * rho * say - 2 * f0_rgb * sby + rho * rho * saa + 2 * rho * f0_rgb * sab + f0_rgb * f0_rgb * sbb
    chi_m = symy - 2 * metal_f0 * smy + metal_f0 * metal_f0 * smm
    chi_d, chi_m = np.maximum(chi_d.sum(axis=1), 0.0), np.maximum(chi_m.sum(axis=1), 0.0)
    metal = chi_m < chi_d
    rho = np.where(metal[:, None], 0.0, rho)
    specular = np.where(metal[:, None], metal_f0, f0_rgb)
    return rho, specular, np.where(metal, chi_m, chi_d), metal


class Columns(NamedTuple):
    """The model's columns per sample and channel (n_lights, N, 3) at one roughness:
    ``diffuse`` = E/π (times ρ), ``coat`` = E·K·F_η(v·h)/F_η(1) (times a dielectric's F0),
    ``metal`` = E·K·(1 − w) (times a metal's F0) and ``metal_offset`` = E·K·w."""

    diffuse: np.ndarray
    coat: np.ndarray
    metal: np.ndarray
    metal_offset: np.ndarray


def coat_fresnel_shape(cos_vh: np.ndarray, ior: float = COAT_IOR) -> np.ndarray:
    """A dielectric's Fresnel reflectance against the angle, over its value at normal incidence.

    Unpolarised, exact (Walter et al. 2007, eq. 22). The shape hardly depends on the index
    between 1.3 and 1.8, so F0 times it is linear in F0 and fits any glaze; Schlick's
    approximation, which glTF uses, is 20 % low at 60° for an index of 1.5.

    >>> round(float(coat_fresnel_shape(np.array(1.0))), 6)
    1.0
    """
    c = np.clip(cos_vh, 1e-6, 1.0)
    g = np.sqrt(ior * ior - 1.0 + c * c)
    f = 0.5 * ((g - c) / (g + c)) ** 2 * (1.0 + ((c * (g + c) - 1.0) / (c * (g - c) + 1.0)) ** 2)
    return f / ((ior - 1.0) / (ior + 1.0)) ** 2


def _design(geometry: Geometry, irradiance: np.ndarray, alpha: float | np.ndarray) -> Columns:
    """The :class:`Columns` of every sample at roughness ``alpha``."""
    k = ggx_lobe(geometry.cos_l, geometry.cos_v, geometry.cos_h, alpha)
    w = np.clip(1.0 - geometry.cos_vh, 0.0, 1.0) ** 5
    lobe = irradiance * k[..., None]
    coat = lobe * coat_fresnel_shape(geometry.cos_vh)[..., None]
    return Columns(irradiance / math.pi, coat, lobe * (1.0 - w)[..., None], lobe * w[..., None])


def predicted_radiance(fit: BRDFFit, irradiance: np.ndarray, geometry: Geometry) -> np.ndarray:
    """What a fitted BRDF sends to the camera under the given irradiance (n_lights, N, 3)."""
    cols = _design(geometry, irradiance, fit.roughness[None, :])
    dielectric = cols.diffuse * fit.diffuse[None] + cols.coat * fit.specular[None]
    metal = cols.metal * fit.specular[None] + cols.metal_offset
    return np.where(fit.metal[None, :, None], metal, dielectric)


def sample_weights(radiance: np.ndarray, used: np.ndarray, floor_fraction: float = 0.02) -> np.ndarray:
    """``1/(L + floor)`` per sample and channel (0 where unused): shot-noise-like weights,
    the floor a share of each point's median radiance so that dark samples do not dominate."""
    lum = np.where(used[..., None], np.nan_to_num(radiance, nan=0.0), np.nan)
    with warnings.catch_warnings():  # points without a used sample: NaN, floored below
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(lum, axis=0)
    floor = floor_fraction * np.nan_to_num(median, nan=1.0) + 1e-12
    wgt = 1.0 / (np.maximum(np.nan_to_num(radiance, nan=0.0), 0.0) + floor[None])
    return np.where(used[..., None], wgt, 0.0)


@numba.njit(cache=True, nogil=True)
def _chi2_kernel(cos_l, cos_v, cos_h, coat_shape, schlick_w, irradiance, y, wgt, alphas, out):  # pragma: no cover
    """χ² of the better material (:func:`_solve_materials`) per point at each α of ``alphas``
    (G, N): the same sums and the same closed-form solve, one point at a time, without the
    (n_lights, N, 3) temporaries of the array version."""
    n_lights, n_points = cos_l.shape
    inv_pi = 1.0 / math.pi
    s = np.zeros((9, 3))
    for n in range(n_points):
        for g in range(alphas.shape[0]):
            a2 = alphas[g, n] * alphas[g, n]
            s[:] = 0.0
            for j in range(n_lights):
                if wgt[j, n, 0] == 0.0 and wgt[j, n, 1] == 0.0 and wgt[j, n, 2] == 0.0:
                    continue
                k = 0.0
                if cos_l[j, n] > 0.0 and cos_v[j, n] > 0.0 and cos_h[j, n] > 0.0:
                    cl = min(max(cos_l[j, n], 1e-6), 1.0)
                    cv = min(max(cos_v[j, n], 1e-6), 1.0)
                    ch = min(cos_h[j, n], 1.0)
                    d = a2 / (math.pi * (ch * ch * (a2 - 1.0) + 1.0) ** 2)
                    lam_l = 0.5 * (math.sqrt(1.0 + a2 * (1.0 - cl * cl) / (cl * cl)) - 1.0)
                    lam_v = 0.5 * (math.sqrt(1.0 + a2 * (1.0 - cv * cv) / (cv * cv)) - 1.0)
                    k = d / (1.0 + lam_l + lam_v) / (4.0 * cl * cv)
                for c in range(3):
                    w, e, yy = wgt[j, n, c], irradiance[j, n, c], y[j, n, c]
                    a = e * inv_pi
                    lobe = e * k
                    b = lobe * coat_shape[j, n]
                    m = lobe * (1.0 - schlick_w[j, n])
                    ym = yy - lobe * schlick_w[j, n]
                    s[0, c] += w * a * a
                    s[1, c] += w * b * b
                    s[2, c] += w * a * b
                    s[3, c] += w * a * yy
                    s[4, c] += w * b * yy
                    s[5, c] += w * yy * yy
                    s[6, c] += w * m * m
                    s[7, c] += w * m * ym
                    s[8, c] += w * ym * ym
            num, den = 0.0, 0.0
            for c in range(3):
                ratio = s[2, c] / s[0, c] if s[0, c] > 0.0 else 0.0
                num += s[4, c] - ratio * s[3, c]
                den += s[1, c] - ratio * s[2, c]
            if den != 0.0:
                f0 = num / den
            else:
                f0 = DIELECTRIC_F0_MAX if num > 0.0 else 0.0
            if not math.isfinite(f0):
                f0 = 0.0 if math.isnan(f0) else (DIELECTRIC_F0_MAX if f0 > 0 else 0.0)
            f0 = min(max(f0, 0.0), DIELECTRIC_F0_MAX)
            chi_d, chi_m = 0.0, 0.0
            for c in range(3):
                saa, sbb, sab, say, sby, syy = s[0, c], s[1, c], s[2, c], s[3, c], s[4, c], s[5, c]
                rho = max((say - sab * f0) / saa, 0.0) if saa > 0.0 else 0.0
                chi_d += syy - 2 * rho * say - 2 * f0 * sby + rho * rho * saa + 2 * rho * f0 * sab + f0 * f0 * sbb
                mf = max(s[7, c] / s[6, c], 0.0) if s[6, c] > 0.0 else 0.0
                chi_m += s[8, c] - 2 * mf * s[7, c] + mf * mf * s[6, c]
            chi_d, chi_m = max(chi_d, 0.0), max(chi_m, 0.0)
            out[g, n] = chi_m if chi_m < chi_d else chi_d


def chi2_of_roughness(
    geometry: Geometry, irradiance: np.ndarray, y: np.ndarray, wgt: np.ndarray, alphas: np.ndarray
) -> np.ndarray:
    """χ² of the better material at every point for each row of ``alphas`` (G, N): the
    compiled :func:`_chi2_kernel` over blocks of points, on as many threads as there are
    cores (one inside a Dask worker, whose processes already share them)."""
    alphas = np.ascontiguousarray(np.broadcast_to(alphas, (len(alphas), y.shape[1])), dtype=float)
    arrays = (
        np.ascontiguousarray(geometry.cos_l, dtype=float),
        np.ascontiguousarray(np.broadcast_to(geometry.cos_v, geometry.cos_l.shape), dtype=float),
        np.ascontiguousarray(geometry.cos_h, dtype=float),
        np.ascontiguousarray(coat_fresnel_shape(geometry.cos_vh), dtype=float),
        np.ascontiguousarray(np.clip(1.0 - geometry.cos_vh, 0.0, 1.0) ** 5, dtype=float),
        np.ascontiguousarray(irradiance, dtype=float),
        np.ascontiguousarray(y, dtype=float),
        np.ascontiguousarray(wgt, dtype=float),
    )
    out = np.empty(alphas.shape)
    n_points = y.shape[1]
    threads = 1 if in_dask_worker() else default_workers()
    blocks = [slice(i, min(i + 2048, n_points)) for i in range(0, n_points, 2048)]

    def block(b: slice) -> None:
        cos_l, cos_v, cos_h, shape, schlick, irr, obs, w = (np.ascontiguousarray(a[:, b]) for a in arrays)
        part = np.empty((alphas.shape[0], b.stop - b.start))
        _chi2_kernel(cos_l, cos_v, cos_h, shape, schlick, irr, obs, w, np.ascontiguousarray(alphas[:, b]), part)
        out[:, b] = part

    if threads > 1 and len(blocks) > 1:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(block, blocks))
    else:
        for b in blocks:
            block(b)
    return out


def _joint_sigmas(
    geometry: Geometry,
    irradiance: np.ndarray,
    alpha: np.ndarray,
    f0: np.ndarray,
    metal: np.ndarray,
    wgt: np.ndarray,
    chi2_red: np.ndarray,
    step: float = 0.02,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1σ of ρ (N, 3), F0 (N, 3) and log α (N,) from each point's Fisher matrix.

    The parameters are the material's own: a dielectric's ρ_R, ρ_G, ρ_B, its grey F0 and
    log α; a metal's F0_R, F0_G, F0_B and log α (its ρ is 0, exactly). ∂L/∂log α comes from
    a central difference of K, so the marginal errors carry the correlations between the
    lobe's height and width and the body colour. The weights are inverse variances up to a
    scale, so the covariance is scaled by the point's own χ² per degree of freedom: the
    residuals' scale, noise and model error together.
    """
    n_points = len(alpha)
    cols = _design(geometry, irradiance, alpha[None, :])
    up = _design(geometry, irradiance, (alpha * math.exp(step))[None, :])
    down = _design(geometry, irradiance, (alpha * math.exp(-step))[None, :])
    is_metal = metal[None, :, None]
    d_alpha = np.where(
        is_metal,
        f0[None] * (up.metal - down.metal) + (up.metal_offset - down.metal_offset),
        f0[None] * (up.coat - down.coat),
    ) / (2.0 * step)  # (n_lights, N, 3)
    a, b_coat, b_metal = cols.diffuse, cols.coat, cols.metal
    # Slots 0-2: ρ_c (dielectric) or F0_c (metal); slot 3: the dielectric's grey F0; slot 4: log α.
    fisher = np.zeros((n_points, 5, 5))
    for c in range(3):
        w = wgt[..., c]
        first = np.where(metal[None, :], b_metal[..., c], a[..., c])
        grey = np.where(metal[None, :], 0.0, b_coat[..., c])
        slots = {c: first, 3: grey, 4: d_alpha[..., c]}
        for i, ci in slots.items():
            for j, cj in slots.items():
                fisher[:, i, j] += np.sum(w * ci * cj, axis=0)
    fisher[metal, 3, 3] = 1.0  # the metal has no grey F0: a unit diagonal keeps the matrix whole
    diag = np.full((n_points, 5), np.inf)
    ok = np.all(np.isfinite(fisher), axis=(1, 2)) & (np.linalg.det(fisher) > 0)
    if ok.any():
        diag[ok] = np.diagonal(np.linalg.pinv(fisher[ok], hermitian=True), axis1=1, axis2=2)
    with np.errstate(invalid="ignore"):  # points without samples: NaN
        sigma = np.sqrt(np.maximum(diag, 0.0) * chi2_red[:, None])
    sigma_rho = np.where(metal[:, None], 0.0, sigma[:, :3])
    sigma_f0 = np.where(metal[:, None], sigma[:, :3], np.repeat(sigma[:, 3:4], 3, axis=1))
    return sigma_rho, sigma_f0, sigma[:, 4]


def _refined_roughness(
    chi: np.ndarray, grid: np.ndarray, chi2_at: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's α from its χ² on the grid (len(grid), N): a parabola through the grid's
    minimum and its neighbours in log α, then two finer ones (a quarter and a sixteenth of
    the step, ``chi2_at`` evaluating χ² anywhere) where χ² is not quadratic over a whole
    step. Returns α, χ²'s curvature in log α there, and whether the minimum lies inside
    the grid with a positive curvature (a width the data pin, not an end of the range)."""
    n_points = chi.shape[1]
    best = np.argmin(chi, axis=0)
    log_grid = np.log(grid)
    inner = np.clip(best, 1, len(grid) - 2)
    rows = np.arange(n_points)
    c_m, c_0, c_p = chi[inner - 1, rows], chi[inner, rows], chi[inner + 1, rows]
    step = log_grid[1] - log_grid[0]
    curvature = (c_p - 2 * c_0 + c_m) / step**2
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curvature > 0, -0.5 * (c_p - c_m) / (step * curvature), 0.0)
    interior = best == inner
    log_alpha = np.where(interior, log_grid[inner] + np.clip(shift, -step, step), log_grid[best])
    for level in (4.0, 16.0):
        h = step / level
        c_m, c_0, c_p = (chi2_at(log_alpha + d) for d in (-h, 0.0, h))
        fine = (c_p - 2 * c_0 + c_m) / h**2
        with np.errstate(divide="ignore", invalid="ignore"):
            move = np.where(fine > 0, -0.5 * (c_p - c_m) / (h * fine), 0.0)
        log_alpha = np.where(interior, log_alpha + np.clip(move, -2 * h, 2 * h), log_alpha)
        curvature = np.where(interior & (fine > 0), fine, curvature)
    return np.exp(log_alpha), curvature, interior & (curvature > 0)


def fit_brdf(
    radiance: np.ndarray,
    irradiance: np.ndarray,
    geometry: Geometry,
    used: np.ndarray,
    *,
    grid: np.ndarray = ROUGHNESS_GRID,
    weights: np.ndarray | None = None,
    min_samples: int = 6,
) -> BRDFFit:
    """Fit ρ, F0 and α per point to its samples.

    Parameters
    ----------
    radiance : ndarray (n_lights, N, 3)
        Linear radiance per sample (the camera's rate over k·⟨cos⁴β⟩).
    irradiance : ndarray (n_lights, N, 3)
        Each channel's irradiance from the light model at each sample.
    geometry : Geometry
        The samples' angles.
    used : ndarray (n_lights, N) of bool
        The samples to fit (lit, not shadowed, not saturated, seen).
    weights : ndarray (n_lights, N, 3), optional
        Inverse variances up to a scale (default :func:`sample_weights`).
    min_samples : int
        Fewer usable samples leave the point unfitted (NaN, confidence 0).

    Returns
    -------
    BRDFFit
        Points whose lobe the data do not pin have confidence :data:`CONFIDENCE_NONE` here;
        :func:`share_lobes` gives them a basis material's lobe.
    """
    n_points = radiance.shape[1]
    y = np.where(used[..., None], np.nan_to_num(radiance, nan=0.0), 0.0)
    wgt = sample_weights(radiance, used) if weights is None else np.where(used[..., None], weights, 0.0)
    chi = chi2_of_roughness(geometry, irradiance, y, wgt, np.asarray(grid, float)[:, None])

    def chi2_at(log_alpha: np.ndarray) -> np.ndarray:
        return chi2_of_roughness(geometry, irradiance, y, wgt, np.exp(log_alpha)[None, :])[0]

    alpha, curvature, pinned_curve = _refined_roughness(chi, grid, chi2_at)

    # The linear parameters at each point's own α, and their covariance.
    n_used = used.sum(axis=0)
    rho, f0, c2, metal = _solve_materials(_design(geometry, irradiance, alpha[None, :]), y, wgt)
    dof = np.maximum(3 * n_used - np.where(metal, 4, 5), 1)
    chi2_red = c2 / dof
    sigma_rho, sigma_f0, sigma_log_alpha = _joint_sigmas(geometry, irradiance, alpha, f0, metal, wgt, chi2_red)
    sigma_alpha = np.where(pinned_curve, alpha * np.nan_to_num(sigma_log_alpha, nan=np.inf), np.inf)

    k_fit = ggx_lobe(geometry.cos_l, geometry.cos_v, geometry.cos_h, alpha[None, :])
    peak = ggx_lobe(np.ones(1), np.ones(1), np.ones(1), alpha)
    highlights = np.sum(used & (k_fit >= 0.25 * peak[None, :]), axis=0)
    # The lobe's peak is only seen where a sample's half vector came within 10° of the
    # normal (its mirror direction was probed); elsewhere a broad lobe and the diffuse part
    # trade off, and a fit can look pinned when it is not.
    probed = np.sum(used & (geometry.cos_h >= math.cos(math.radians(PROBE_DEG))), axis=0) >= 1
    significant = f0.mean(axis=1) > 3.0 * sigma_f0.mean(axis=1)
    enough = n_used >= min_samples
    # A point the model does not explain (a superpixel astride two facets sees two
    # highlights; a cast shadow's edge) fits a broad, bright lobe that is no material's:
    # its χ² stands out from the other points' (the weights share one scale).
    typical = float(np.median(chi2_red[enough])) if enough.any() else 0.0
    explained = chi2_red <= OUTLIER_CHI2 * typical
    pinned = pinned_curve & (sigma_alpha < 0.5 * alpha) & significant & (highlights >= 1) & probed & explained
    # A matte point: its mirror direction was probed and no lobe answered, F0 + 2σ below
    # half a glaze's. It is known to have no lobe (F0 as fitted, near 0; α 1, the widest),
    # which is not the same as not knowing.
    matte = enough & ~pinned & probed & (f0.mean(axis=1) + 2.0 * sigma_f0.mean(axis=1) < MATTE_F0)
    alpha = np.where(matte, 1.0, alpha)
    sigma_alpha = np.where(matte, np.nan, sigma_alpha)
    confidence = np.where(enough & (pinned | matte), CONFIDENCE_OWN, CONFIDENCE_NONE).astype(np.uint8)
    nan3 = np.full((n_points, 3), np.nan)
    return BRDFFit(
        diffuse=np.where(enough[:, None], rho, nan3),
        specular=np.where(enough[:, None], f0, nan3),
        roughness=np.where(enough, alpha, np.nan),
        sigma_diffuse=np.where(enough[:, None], sigma_rho, nan3),
        sigma_specular=np.where(enough[:, None], sigma_f0, nan3),
        sigma_roughness=np.where(enough, sigma_alpha, np.nan),
        chi2=np.where(enough, chi2_red, np.nan),
        samples=n_used,
        highlights=highlights,
        confidence=confidence,
        metal=metal & enough,
    )


def _colour_features(diffuse: np.ndarray) -> np.ndarray:
    """Chromaticity and log brightness of diffuse albedos (N, 3): what clusters materials."""
    total = np.maximum(diffuse.sum(axis=1, keepdims=True), 1e-6)
    return np.column_stack([diffuse[:, :2] / total, 0.25 * np.log(total[:, 0])])


def basis_materials(fit: BRDFFit, own: np.ndarray, max_basis: int, seed: int) -> list[dict[str, Any]]:
    """The materials of the points whose lobe is pinned (``own``): k-means of their colour
    (see :func:`share_lobes`), each with the median F0 and α of its members, their spread
    as the 1σ, and whether it is a metal."""
    from scipy.cluster.vq import kmeans, vq  # noqa: PLC0415 - only where lobes are shared

    features = _colour_features(np.maximum(fit.diffuse[own] + fit.specular[own], 0.0))
    smallest = max(10, int(0.005 * len(features)))  # a material of its own: 0.5 % of the pinned points
    k = max(1, min(max_basis, len(features) // smallest))
    # The best of 10 k-means runs (least distortion), seeded: the same bases every time.
    centres, _ = kmeans(features, k, iter=10, seed=seed) if k > 1 else (features.mean(axis=0)[None], 0.0)
    labels, _ = vq(features, centres)
    # Clusters too small to be a material (stray colours at edges) give their points to the
    # others, and clusters of one colour are one material (k-means splits a large one).
    kept = np.flatnonzero(np.bincount(labels, minlength=len(centres)) >= smallest)
    centres = centres[kept] if kept.size else features.mean(axis=0)[None]
    labels, _ = vq(features, centres)
    order = np.argsort(-np.bincount(labels, minlength=len(centres)))
    merged: list[int] = []
    for c in order:
        if all(np.linalg.norm(centres[c] - centres[m]) > SAME_COLOUR for m in merged):
            merged.append(int(c))
    centres = centres[merged]
    labels, _ = vq(features, centres)
    basis = []
    for c in range(len(centres)):
        members = labels == c
        f0 = np.median(fit.specular[own][members], axis=0)
        typical = float(np.exp(np.median(np.log(fit.roughness[own][members]))))
        basis.append(
            {
                "diffuse": np.median(fit.diffuse[own][members], axis=0).tolist(),
                "specular": f0.tolist(),
                "roughness": typical,
                "sigma_specular": (1.4826 * np.median(np.abs(fit.specular[own][members] - f0), axis=0)).tolist(),
                "sigma_roughness": float(
                    typical * 1.4826 * np.median(np.abs(np.log(fit.roughness[own][members]) - math.log(typical)))
                ),
                "points": int(members.sum()),
                "metal": bool(np.mean(fit.metal[own][members]) > 0.5),
            }
        )
    return basis


def share_lobes(
    fit: BRDFFit,
    radiance: np.ndarray,
    irradiance: np.ndarray,
    geometry: Geometry,
    used: np.ndarray,
    *,
    max_basis: int = 6,
    seed: int = 0,
    weights: np.ndarray | None = None,
) -> BRDFFit:
    """Give the points whose lobe is not pinned the lobe of the nearest basis material.

    The basis materials are k-means clusters (scipy's ``kmeans``, the best of 10 runs, with
    ``max_basis`` centres; those holding less than 0.5 % of the pinned points are dropped
    and their points given to the nearest others) of the pinned points' colour (diffuse
    plus specular reflectance: a metal's colour is its F0); each basis has the median F0
    and α of its members. An unpinned point takes the basis whose lobe, with the point's
    albedo refitted under it, explains its samples best (its own colour can mislead: a
    point whose lobe was never seen may have split diffuse and specular wrongly), and its
    confidence becomes :data:`CONFIDENCE_SHARED`; its 1σ of F0 and
    α are the spread of the basis (a borrowed value is no better known than that).
    Without pinned points nothing changes.
    """

    own = fit.confidence == CONFIDENCE_OWN
    fitted = np.isfinite(fit.roughness)
    borrow = fitted & ~own
    if not own.any() or not borrow.any():
        return fit
    basis = basis_materials(fit, own, max_basis, seed)
    index = np.flatnonzero(borrow)
    sub = (slice(None), index)
    sub_geometry = Geometry(geometry.cos_l[sub], geometry.cos_v[sub], geometry.cos_h[sub], geometry.cos_vh[sub])
    u = used[sub]
    observed = np.where(u[..., None], np.nan_to_num(radiance[sub], nan=0.0), 0.0)
    wgt = sample_weights(radiance[sub], u) if weights is None else np.where(u[..., None], weights[sub], 0.0)
    # Each basis's lobe, the body colour refitted under it; the point takes the one that
    # explains its own samples best (its colour alone can mislead: a point whose lobe was
    # never seen may have fitted a wrong share of diffuse and specular).
    best_chi = np.full(len(index), np.inf)
    nearest = np.zeros(len(index), np.int64)
    rho = np.zeros((len(index), 3))
    sigma_rho = np.full((len(index), 3), np.inf)
    for c, material in enumerate(basis):
        cols = _design(sub_geometry, irradiance[sub], material["roughness"])
        f0 = np.asarray(material["specular"])[None, None, :]
        a = cols.diffuse
        y = observed - (cols.metal_offset + f0 * cols.metal if material["metal"] else f0 * cols.coat)
        saa = np.sum(wgt * a * a, axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            body = 0.0 if material["metal"] else np.maximum(np.sum(wgt * a * y, axis=0) / saa, 0.0)
            chi = np.sum(wgt * (y - body * a) ** 2, axis=(0, 2))
            sigma = np.sqrt(1.0 / saa)
        better = chi < best_chi
        best_chi[better], nearest[better] = chi[better], c
        rho[better] = np.broadcast_to(body, rho.shape)[better]
        sigma_rho[better] = np.where(material["metal"], 0.0, sigma)[better]
    resid = best_chi / np.maximum(3 * u.sum(axis=0) - 3, 1)
    sigma_rho = sigma_rho * np.sqrt(resid)[:, None]
    alpha = np.array([basis[c]["roughness"] for c in nearest])
    f0 = np.array([basis[c]["specular"] for c in nearest])
    borrowed_metal = np.array([basis[c]["metal"] for c in nearest], dtype=bool)
    out = copy.deepcopy(fit)
    out.diffuse[index] = rho
    out.sigma_diffuse[index] = sigma_rho
    out.specular[index] = f0
    out.roughness[index] = alpha
    out.sigma_specular[index] = np.array([basis[c]["sigma_specular"] for c in nearest])
    out.sigma_roughness[index] = np.array([basis[c]["sigma_roughness"] for c in nearest])
    out.chi2[index] = resid
    out.confidence[index] = CONFIDENCE_SHARED
    out.metal[index] = borrowed_metal
    out.basis = basis
    return out


@dataclass
class MaterialResult:
    """Per light model, the fitted reflectance of every point, and the relighting check."""

    fits: dict[str, BRDFFit]
    fitted_lights: np.ndarray  # indices of the light positions the fits used
    held_out: np.ndarray  # indices of the positions left out for relighting
    relighting: dict[str, dict[str, Any]] = field(default_factory=dict)
    sigma_scale: dict[str, dict[str, float]] = field(default_factory=dict)  # per model, the 1σ's neighbour scale
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """Per light model: medians of the parameters over the points with their own lobe,
        the shares per confidence, the basis materials and the relighting error."""
        out: dict[str, Any] = {
            "fitted_positions": self.fitted_lights.tolist(),
            "held_out_positions": self.held_out.tolist(),
            "notes": list(self.notes),
            "methods": {},
        }
        for method, fit in self.fits.items():
            fitted = np.isfinite(fit.roughness)
            own = fit.confidence == CONFIDENCE_OWN
            counts = {
                name: int(np.sum(fit.confidence[fitted] == code))
                for name, code in (("own", CONFIDENCE_OWN), ("shared", CONFIDENCE_SHARED), ("none", CONFIDENCE_NONE))
            }
            stats: dict[str, Any] = {"points": int(fitted.sum()), "confidence": counts, "basis": fit.basis}
            if own.any():
                stats.update(
                    diffuse_median=np.median(fit.diffuse[own], axis=0).tolist(),
                    specular_median=np.median(fit.specular[own], axis=0).tolist(),
                    roughness_median=float(np.median(fit.roughness[own])),
                    chi2_median=float(np.median(fit.chi2[own])),
                )
            stats["relighting"] = self.relighting.get(method, {})
            stats["sigma_scale"] = self.sigma_scale.get(method, {})
            out["methods"][method] = stats
        return out

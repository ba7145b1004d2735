"""An object's whole reflectance per point: diffuse albedo, specular reflectance and roughness.

Every usable (light, point) sample of an object run is a linear radiance ``L`` (R, G, B),
the irradiance ``E`` the light model gives there, the direction ``l`` towards the light and
``v`` towards the camera. The model fitted per point is a Lambertian part and a GGX
microfacet lobe with Smith's height-correlated masking–shadowing and Schlick's Fresnel::

    L_c = E_c · (ρ_c/π + K·(F0_c·(1 − w) + w)),   K = D(h)·G₂(l, v) / (4 (n·l)(n·v)),
    w = (1 − v·h)⁵

with ρ the diffuse albedo, F0 the specular reflectance at normal incidence (about 0.04 for
glazes, varnishes and lacquers, tinted and high for metals) and α the roughness in D and
G₂. For a fixed α the model is linear in ρ_c and F0_c, so each channel is a weighted 2 × 2
least-squares problem; α is searched on a log grid shared by the three channels and refined
by a parabola through the χ² minimum (the variable projection of Golub & Pereyra, 1973).

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
from dataclasses import dataclass, field

import numpy as np

#: Roughness values searched (GGX α): from a polished lacquer to a nearly Lambertian lobe.
ROUGHNESS_GRID = np.geomspace(0.02, 1.0, 36)

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
    basis: list[dict] = field(default_factory=list)

    @property
    def metalness(self) -> np.ndarray:
        """1 where the specular reflectance is a metal's (bright, and no diffuse part beside it).

        Dielectrics reflect at most ~0.1 at normal incidence (an index below 2); a metal's
        F0 is above ~0.5 and it has no body colour. The blend between is linear in the
        share of the specular in the total reflectance.
        """
        f0 = self.specular.mean(axis=1)
        rho = self.diffuse.mean(axis=1)
        share = f0 / np.maximum(f0 + rho, 1e-9)
        return np.clip((f0 - 0.15) / 0.35, 0.0, 1.0) * np.clip((share - 0.5) / 0.3, 0.0, 1.0)


def _solve_two(
    a: np.ndarray, b: np.ndarray, y: np.ndarray, wgt: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted ``y ≈ x₁·a + x₂·b`` with x ≥ 0 per column (samples along axis 0).

    Returns x₁, x₂, the χ² and the inverse normal matrix (its 2 × 2 entries as (3, ...)).
    """
    saa = np.sum(wgt * a * a, axis=0)
    sbb = np.sum(wgt * b * b, axis=0)
    sab = np.sum(wgt * a * b, axis=0)
    say = np.sum(wgt * a * y, axis=0)
    sby = np.sum(wgt * b * y, axis=0)
    syy = np.sum(wgt * y * y, axis=0)
    det = saa * sbb - sab * sab
    ok = det > 1e-12 * np.maximum(saa * sbb, 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        x1 = np.where(ok, (sbb * say - sab * sby) / det, 0.0)
        x2 = np.where(ok, (saa * sby - sab * say) / det, 0.0)
        only_a = np.where(saa > 0, say / saa, 0.0)
        only_b = np.where(sbb > 0, sby / sbb, 0.0)
    # Non-negativity: where the pair leaves the quadrant, the better of the two one-term fits.
    out = ~ok | (x1 < 0) | (x2 < 0)
    chi_a = syy - np.maximum(only_a, 0.0) * say
    chi_b = syy - np.maximum(only_b, 0.0) * sby
    use_a = chi_a <= chi_b
    x1 = np.where(out, np.where(use_a, np.maximum(only_a, 0.0), 0.0), x1)
    x2 = np.where(out, np.where(use_a, 0.0, np.maximum(only_b, 0.0)), x2)
    chi2 = syy - 2 * x1 * say - 2 * x2 * sby + x1 * x1 * saa + 2 * x1 * x2 * sab + x2 * x2 * sbb
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([sbb / det, saa / det, -sab / det])
    inv = np.where(ok, inv, np.stack([1.0 / np.maximum(saa, 1e-300), 1.0 / np.maximum(sbb, 1e-300), 0.0 * saa]))
    return x1, x2, np.maximum(chi2, 0.0), inv


def _design(
    geometry: Geometry, irradiance: np.ndarray, alpha: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sample and channel: the diffuse column ``E/π``, the specular column ``E·K·(1 − w)``
    and the offset ``E·K·w`` (n_lights, N, 3)."""
    k = ggx_lobe(geometry.cos_l, geometry.cos_v, geometry.cos_h, alpha)
    w = np.clip(1.0 - geometry.cos_vh, 0.0, 1.0) ** 5
    diffuse = irradiance / math.pi
    lobe = irradiance * k[..., None]
    return diffuse, lobe * (1.0 - w)[..., None], lobe * w[..., None]


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


def _joint_sigmas(
    geometry: Geometry,
    irradiance: np.ndarray,
    alpha: np.ndarray,
    f0: np.ndarray,
    wgt: np.ndarray,
    chi2_red: np.ndarray,
    step: float = 0.02,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1σ of ρ (N, 3), F0 (N, 3) and log α (N,) from the 7 × 7 Fisher matrix of each point.

    The columns are ∂L/∂ρ_c, ∂L/∂F0_c (each one channel) and ∂L/∂log α (every channel, by
    a central difference of K), so the marginal errors carry the correlations between the
    lobe's height and width and the body colour. The weights are inverse variances up to a
    scale, so the covariance is scaled by the point's own χ² per degree of freedom: the
    residuals' scale, noise and model error together.
    """
    n_points = len(alpha)
    a, b, _ = _design(geometry, irradiance, alpha[None, :])
    up = _design(geometry, irradiance, (alpha * math.exp(step))[None, :])
    down = _design(geometry, irradiance, (alpha * math.exp(-step))[None, :])
    d_alpha = (f0[None] * (up[1] - down[1]) + (up[2] - down[2])) / (2.0 * step)  # (n_lights, N, 3)
    fisher = np.zeros((n_points, 7, 7))
    for c in range(3):
        w = wgt[..., c]
        cols = (a[..., c], b[..., c], d_alpha[..., c])
        index = (c, 3 + c, 6)
        for i, ci in zip(index, cols, strict=True):
            for j, cj in zip(index, cols, strict=True):
                fisher[:, i, j] += np.sum(w * ci * cj, axis=0)
    scale = chi2_red
    diag = np.full((n_points, 7), np.inf)
    ok = np.all(np.isfinite(fisher), axis=(1, 2)) & (np.linalg.det(fisher) > 0)
    if ok.any():
        diag[ok] = np.diagonal(np.linalg.pinv(fisher[ok], hermitian=True), axis1=1, axis2=2)
    with np.errstate(invalid="ignore"):  # points without samples: NaN
        sigma = np.sqrt(np.maximum(diag, 0.0) * scale[:, None])
    return sigma[:, :3], sigma[:, 3:6], sigma[:, 6]


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
    chi = np.empty((len(grid), n_points))
    for g, alpha in enumerate(grid):
        a, b, o = _design(geometry, irradiance, float(alpha))
        _, _, c2, _ = _solve_two(a, b, y - o, wgt)
        chi[g] = c2.sum(axis=-1)
    best = np.argmin(chi, axis=0)
    log_grid = np.log(grid)

    def chi2_at(log_alpha: np.ndarray) -> np.ndarray:
        a, b, o = _design(geometry, irradiance, np.exp(log_alpha)[None, :])
        return _solve_two(a, b, y - o, wgt)[2].sum(axis=-1)

    # A parabola through the minimum and its neighbours, in log α.
    inner = np.clip(best, 1, len(grid) - 2)
    rows = np.arange(n_points)
    c_m, c_0, c_p = chi[inner - 1, rows], chi[inner, rows], chi[inner + 1, rows]
    step = log_grid[1] - log_grid[0]
    curvature = (c_p - 2 * c_0 + c_m) / step**2
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(curvature > 0, -0.5 * (c_p - c_m) / (step * curvature), 0.0)
    shift = np.clip(shift, -step, step)
    log_alpha = np.where(best == inner, log_grid[inner] + shift, log_grid[best])
    # Two finer parabolas about the estimate (a quarter, then a sixteenth of the grid step):
    # the grid's parabola is biased where χ² is not quadratic over a whole step.
    interior = best == inner
    for level in (4.0, 16.0):
        h = step / level
        c_m, c_0, c_p = (chi2_at(log_alpha + d) for d in (-h, 0.0, h))
        fine = (c_p - 2 * c_0 + c_m) / h**2
        with np.errstate(divide="ignore", invalid="ignore"):
            move = np.where(fine > 0, -0.5 * (c_p - c_m) / (h * fine), 0.0)
        log_alpha = np.where(interior, log_alpha + np.clip(move, -2 * h, 2 * h), log_alpha)
        curvature = np.where(interior & (fine > 0), fine, curvature)
    alpha = np.exp(log_alpha)

    # The linear parameters at each point's own α, and their covariance.
    n_used = used.sum(axis=0)
    a, b, o = _design(geometry, irradiance, alpha[None, :])  # alpha broadcasts over the lights
    rho, f0, c2, inv = _solve_two(a, b, y - o, wgt)
    dof = np.maximum(3 * n_used - 7, 1)
    chi2_red = c2.sum(axis=-1) / dof
    pinned_curve = (best > 0) & (best < len(grid) - 1) & (curvature > 0)
    sigma_rho, sigma_f0, sigma_log_alpha = _joint_sigmas(geometry, irradiance, alpha, f0, wgt, chi2_red)
    sigma_alpha = np.where(pinned_curve, alpha * np.nan_to_num(sigma_log_alpha, nan=np.inf), np.inf)

    k_fit = ggx_lobe(geometry.cos_l, geometry.cos_v, geometry.cos_h, alpha[None, :])
    peak = ggx_lobe(np.ones(1), np.ones(1), np.ones(1), alpha)
    highlights = np.sum(used & (k_fit >= 0.25 * peak[None, :]), axis=0)
    significant = f0.mean(axis=1) > 3.0 * sigma_f0.mean(axis=1)
    pinned = pinned_curve & (sigma_alpha < 0.5 * alpha) & significant & (highlights >= 1)
    enough = n_used >= min_samples
    confidence = np.where(enough & pinned, CONFIDENCE_OWN, CONFIDENCE_NONE).astype(np.uint8)
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
    )


def _colour_features(diffuse: np.ndarray) -> np.ndarray:
    """Chromaticity and log brightness of diffuse albedos (N, 3): what clusters materials."""
    total = np.maximum(diffuse.sum(axis=1, keepdims=True), 1e-6)
    return np.column_stack([diffuse[:, :2] / total, 0.25 * np.log(total[:, 0])])


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

    The basis materials are k-means clusters (scipy's ``kmeans2``, k chosen as the largest
    up to ``max_basis`` whose clusters each hold at least 2 % of the pinned points) of the
    pinned points' diffuse colour; each basis has the median F0 and α of its members. An
    unpinned point takes the basis nearest in diffuse colour, its albedo is refitted with
    that lobe fixed, and its confidence becomes :data:`CONFIDENCE_SHARED`; its 1σ of F0 and
    α are the spread of the basis (a borrowed value is no better known than that).
    Without pinned points nothing changes.
    """
    from scipy.cluster.vq import kmeans2  # noqa: PLC0415 - only where lobes are shared

    own = fit.confidence == CONFIDENCE_OWN
    fitted = np.isfinite(fit.roughness)
    borrow = fitted & ~own
    if not own.any() or not borrow.any():
        return fit
    features = _colour_features(np.maximum(fit.diffuse[own], 0.0))
    rng = np.random.default_rng(seed)
    labels, centres = np.zeros(int(own.sum()), np.int64), features.mean(axis=0, keepdims=True)
    for k in range(min(max_basis, int(own.sum()) // 50), 1, -1):
        centres_k, labels_k = kmeans2(features, k, minit="++", seed=rng)
        if np.bincount(labels_k, minlength=k).min() >= 0.02 * len(labels_k):
            labels, centres = labels_k, centres_k
            break
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
            }
        )
    index = np.flatnonzero(borrow)
    distance = np.linalg.norm(
        _colour_features(np.maximum(fit.diffuse[index], 0.0))[:, None, :] - centres[None], axis=-1
    )
    nearest = np.argmin(distance, axis=1)
    alpha = np.array([basis[c]["roughness"] for c in nearest])
    f0 = np.array([basis[c]["specular"] for c in nearest])
    sub = (slice(None), index)
    a, b, o = _design(
        Geometry(geometry.cos_l[sub], geometry.cos_v[sub], geometry.cos_h[sub], geometry.cos_vh[sub]),
        irradiance[sub],
        alpha[None, :],
    )
    u = used[sub]
    y = np.where(u[..., None], np.nan_to_num(radiance[sub], nan=0.0), 0.0) - o - f0[None] * b
    wgt = sample_weights(radiance[sub], u) if weights is None else np.where(u[..., None], weights[sub], 0.0)
    saa = np.sum(wgt * a * a, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.maximum(np.sum(wgt * a * y, axis=0) / saa, 0.0)
        resid = np.sum(wgt * (y - rho[None] * a) ** 2, axis=(0, 2)) / np.maximum(3 * u.sum(axis=0) - 3, 1)
        sigma_rho = np.sqrt(1.0 / saa) * np.sqrt(resid)[:, None]
    out = copy.deepcopy(fit)
    out.diffuse[index] = rho
    out.sigma_diffuse[index] = sigma_rho
    out.specular[index] = f0
    out.roughness[index] = alpha
    out.sigma_specular[index] = np.array([basis[c]["sigma_specular"] for c in nearest])
    out.sigma_roughness[index] = np.array([basis[c]["sigma_roughness"] for c in nearest])
    out.chi2[index] = resid
    out.confidence[index] = CONFIDENCE_SHARED
    out.basis = basis
    return out

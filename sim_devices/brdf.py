"""The simulated objects' reflectance: a Lambertian diffuse part plus a GGX microfacet lobe.

This is the ground truth the reflectance tests trust, written from the papers and checked
against an independent renderer's BSDFs (Mitsuba 3, ``tests/test_sim_brdf.py``); it shares
nothing with :mod:`processing`. With ``l`` the unit vector towards the light, ``v`` towards
the camera, ``n`` the normal and ``h = (l + v)/|l + v|``::

    f(l, v) = (1 − m)·ρ/π + D(h)·G₂(l, v)·F(v·h) / (4 (n·l)(n·v))

    D(h)   = α² / (π ((n·h)²(α² − 1) + 1)²)                  GGX / Trowbridge–Reitz
    G₂     = 1 / (1 + Λ(l) + Λ(v))                            Smith, height-correlated
    Λ(w)   = (−1 + √(1 + α² tan²θ_w)) / 2
    F      = (1 − m)·s·F_η(v·h) + m·(F₀ + (1 − F₀)(1 − v·h)⁵)

- ρ (R, G, B) is the diffuse albedo, and for a metal (m = 1) the tinted reflectance at
  normal incidence F₀ (the glTF "base colour" convention);
- α the GGX roughness (the distribution's own width, not its square root);
- s the dielectric's specular weight (0 a matte surface, 1 a full coat) and F_η the exact,
  unpolarised Fresnel reflectance of a dielectric of index η in air;
- m the metalness, which blends the dielectric (diffuse plus coat) and the conductor.

The diffuse and specular parts add: the diffuse part is not dimmed by the coat's
reflection, so at grazing angles a full coat over a white body returns a few per cent more
than it receives. That is the split most real-time and capture models make (glTF's differs
only in that factor), and a surface file is refused where ρ + s·F_η(1) exceeds 1 at
normal incidence.

References: Walter, Marschner, Li & Torrance, "Microfacet models for refraction through
rough surfaces", EGSR 2007 (D and the Fresnel formula, eq. 22); Heitz, "Understanding the
masking-shadowing function in microfacet-based BRDFs", JCGT 3(2), 2014 (Λ, eq. 72 and 86;
the height-correlated G₂, eq. 99); Schlick, "An inexpensive BRDF model for physically-based
rendering", 1994 (the tinted-F₀ conductor).

>>> import numpy as np
>>> float(ggx_distribution(np.array(1.0), 1.0)) * np.pi    # α = 1: D is uniform, 1/π
1.0
>>> round(float(fresnel_dielectric(np.array(1.0), 1.5)), 4)  # glass at normal incidence
0.04
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


def ggx_distribution(cos_h: ArrayLike, alpha: ArrayLike) -> np.ndarray:
    """GGX normal distribution D at microfacet normals ``cos_h = n·h`` (0 below the surface)."""
    c = np.asarray(cos_h, dtype=float)
    a2 = np.asarray(alpha, dtype=float) ** 2
    c2 = c * c
    return np.where(c > 0.0, a2 / (math.pi * (c2 * (a2 - 1.0) + 1.0) ** 2), 0.0)


def smith_lambda(cos_theta: ArrayLike, alpha: ArrayLike) -> np.ndarray:
    """Smith's Λ for GGX in a direction at ``cos_theta`` to the normal (Heitz 2014, eq. 86)."""
    c = np.clip(np.asarray(cos_theta, dtype=float), 1e-12, 1.0)
    tan2 = (1.0 - c * c) / (c * c)
    return 0.5 * (np.sqrt(1.0 + np.asarray(alpha, dtype=float) ** 2 * tan2) - 1.0)


def smith_masking(cos_theta: ArrayLike, alpha: ArrayLike) -> np.ndarray:
    """G₁, the share of microfacets visible from one direction: ``1 / (1 + Λ)``."""
    return 1.0 / (1.0 + smith_lambda(cos_theta, alpha))


def smith_masking_shadowing(
    cos_l: ArrayLike, cos_v: ArrayLike, alpha: ArrayLike, *, correlated: bool = True
) -> np.ndarray:
    """G₂: height-correlated ``1/(1 + Λ(l) + Λ(v))`` (Heitz eq. 99), or separable ``G₁·G₁``.

    The separable form is what Mitsuba 3 evaluates; the tests compare with it, the renderer
    uses the height-correlated one (a rough surface's heights make masking and shadowing
    correlated, so the separable form shadows too much at grazing angles).
    """
    lam_l, lam_v = smith_lambda(cos_l, alpha), smith_lambda(cos_v, alpha)
    if correlated:
        return 1.0 / (1.0 + lam_l + lam_v)
    return 1.0 / ((1.0 + lam_l) * (1.0 + lam_v))


def fresnel_dielectric(cos_i: ArrayLike, ior: ArrayLike) -> np.ndarray:
    """Unpolarised Fresnel reflectance from air onto a dielectric of index ``ior``.

    Walter et al. 2007, eq. 22: with ``c = cos θ_i`` and ``g = √(η² − 1 + c²)``,
    ``F = ½ ((g − c)/(g + c))² (1 + ((c(g + c) − 1)/(c(g − c) + 1))²)``.
    """
    c = np.clip(np.asarray(cos_i, dtype=float), 0.0, 1.0)
    g = np.sqrt(np.asarray(ior, dtype=float) ** 2 - 1.0 + c * c)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (g - c) / (g + c)
        b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return np.nan_to_num(0.5 * a * a * (1.0 + b * b), nan=1.0)


def fresnel_schlick(cos_i: ArrayLike, f0: ArrayLike) -> np.ndarray:
    """Schlick's approximation with a tinted reflectance ``f0`` at normal incidence."""
    c = np.clip(np.asarray(cos_i, dtype=float), 0.0, 1.0)
    f0 = np.asarray(f0, dtype=float)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


@dataclass(frozen=True)
class Finish:
    """The gloss parameters at N surface points, each an array (N,)."""

    roughness: np.ndarray  # GGX α
    specular: np.ndarray  # the dielectric's specular weight s
    ior: np.ndarray  # the dielectric's index η
    metalness: np.ndarray  # m

    @classmethod
    def matte(cls, count: int) -> Finish:
        zero = np.zeros(count)
        return cls(roughness=np.ones(count), specular=zero, ior=np.full(count, 1.5), metalness=zero)

    @property
    def glossy(self) -> np.ndarray:
        """True where the surface has a specular lobe at all."""
        return (self.specular > 0.0) | (self.metalness > 0.0)

    def take(self, index: np.ndarray) -> Finish:
        return Finish(self.roughness[index], self.specular[index], self.ior[index], self.metalness[index])


def specular_lobe(
    light: np.ndarray,
    view: np.ndarray,
    normal: np.ndarray,
    albedo: np.ndarray,
    finish: Finish,
    *,
    correlated: bool = True,
) -> np.ndarray:
    """The microfacet part of f (N, 3) for unit vectors ``light``, ``view``, ``normal`` (N, 3).

    0 where either direction lies below the surface. ``albedo`` (N, 3) is the conductor's F₀
    where ``finish.metalness`` > 0.
    """
    half = light + view
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    cos_l = np.einsum("ij,ij->i", normal, light)
    cos_v = np.einsum("ij,ij->i", normal, view)
    cos_h = np.einsum("ij,ij->i", normal, half)
    cos_vh = np.einsum("ij,ij->i", view, half)
    above = (cos_l > 0.0) & (cos_v > 0.0)
    alpha = finish.roughness
    d = ggx_distribution(cos_h, alpha)
    g = smith_masking_shadowing(cos_l, cos_v, alpha, correlated=correlated)
    scale = np.where(above, d * g / (4.0 * np.where(above, cos_l * cos_v, 1.0)), 0.0)
    m = finish.metalness[:, None]
    fresnel = (1.0 - m) * (finish.specular * fresnel_dielectric(cos_vh, finish.ior))[:, None]
    fresnel = fresnel + m * fresnel_schlick(cos_vh[:, None], albedo)
    return scale[:, None] * fresnel


def brdf(
    light: np.ndarray,
    view: np.ndarray,
    normal: np.ndarray,
    albedo: np.ndarray,
    finish: Finish,
    *,
    correlated: bool = True,
) -> np.ndarray:
    """The whole f(l, v) (N, 3), per steradian: the diffuse part plus :func:`specular_lobe`."""
    cos_l = np.einsum("ij,ij->i", normal, light)
    cos_v = np.einsum("ij,ij->i", normal, view)
    above = ((cos_l > 0.0) & (cos_v > 0.0))[:, None]
    diffuse = np.where(above, (1.0 - finish.metalness)[:, None] * albedo / math.pi, 0.0)
    return diffuse + specular_lobe(light, view, normal, albedo, finish, correlated=correlated)

"""The simulator's BRDF (sim_devices.brdf) against Mitsuba 3's BSDFs and against integrals.

Mitsuba 3 is an independent renderer (its own C++ GGX, Smith and Fresnel code): where it
evaluates the same model the numbers must agree to its single precision. Mitsuba's
``eval`` returns ``f·cos θ`` towards ``wo`` (the light) with ``si.wi`` towards the camera,
and its masking is separable (``G₁·G₁``); the renderer's height-correlated form is checked
by the integrals instead: the white furnace of D and of G₁ (Heitz 2014, eq. 18 and 20) and
the directional albedo, which must lie between the separable one and 1.
"""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from sim_devices.brdf import (
    Finish,
    brdf,
    fresnel_dielectric,
    ggx_distribution,
    smith_masking,
    smith_masking_shadowing,
    specular_lobe,
)

mi.set_variant("scalar_rgb")

ALPHAS = (0.05, 0.15, 0.35, 0.8)
REL = 2e-4  # Mitsuba's single precision


def directions(count: int, seed: int, min_cos: float = 0.05) -> np.ndarray:
    """Unit vectors in the upper hemisphere, uniform in solid angle, not too grazing."""
    rng = np.random.default_rng(seed)
    cos = rng.uniform(min_cos, 1.0, count)
    phi = rng.uniform(0.0, 2.0 * math.pi, count)
    sin = np.sqrt(1.0 - cos * cos)
    return np.column_stack([sin * np.cos(phi), sin * np.sin(phi), cos])


def finish(count: int, *, alpha: float, specular: float = 1.0, ior: float = 1.5, metalness: float = 0.0) -> Finish:
    return Finish(
        roughness=np.full(count, alpha),
        specular=np.full(count, specular),
        ior=np.full(count, ior),
        metalness=np.full(count, metalness),
    )


def mitsuba_eval(bsdf: mi.BSDF, view: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Mitsuba's f (RGB) for one pair of directions in the local frame (normal +z)."""
    si = mi.SurfaceInteraction3f()
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.wi = mi.Vector3f(*view)
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*light))
    return np.array([value[0], value[1], value[2]]) / light[2]


def pairs(seed: int, count: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    view, light = directions(count, seed), directions(count, seed + 1)
    return view, light, np.tile([0.0, 0.0, 1.0], (count, 1))


@pytest.mark.parametrize("alpha", ALPHAS)
def test_ggx_distribution_and_smith_masking_are_mitsubas(alpha):
    view, light, normal = pairs(seed=1)
    half = (view + light) / np.linalg.norm(view + light, axis=1, keepdims=True)
    dist = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, alpha)
    for v, to_light, h in zip(view, light, half, strict=True):
        hm, vm, lm = mi.Vector3f(*h), mi.Vector3f(*v), mi.Vector3f(*to_light)
        assert float(ggx_distribution(h[2], alpha)) == pytest.approx(dist.eval(hm), rel=REL)
        assert float(smith_masking(v[2], alpha)) == pytest.approx(dist.smith_g1(vm, hm), rel=REL)
        separable = smith_masking_shadowing(to_light[2], v[2], alpha, correlated=False)
        assert float(separable) == pytest.approx(dist.G(vm, lm, hm), rel=REL)


@pytest.mark.parametrize("alpha", ALPHAS)
@pytest.mark.parametrize("ior", [1.33, 1.5, 1.9])
def test_a_dielectric_coat_is_mitsubas_roughplastic_without_its_body(alpha, ior):
    view, light, normal = pairs(seed=2)
    ours = specular_lobe(
        light, view, normal, np.zeros((len(view), 3)), finish(len(view), alpha=alpha, ior=ior), correlated=False
    )
    plastic = mi.load_dict(
        {
            "type": "roughplastic",
            "distribution": "ggx",
            "alpha": alpha,
            "int_ior": ior,
            "ext_ior": 1.0,
            "diffuse_reflectance": {"type": "rgb", "value": 0.0},
        }
    )
    for i in range(len(view)):
        assert ours[i] == pytest.approx(mitsuba_eval(plastic, view[i], light[i]), rel=REL, abs=1e-7)


@pytest.mark.parametrize("alpha", ALPHAS)
def test_a_conductor_is_mitsubas_roughconductor(alpha):
    # Mitsuba's conductor with material "none" reflects F = 1 times its tint: the same as a
    # Schlick conductor with F0 = 1 anywhere, and with a tinted F0 where v = l (v·h = 1).
    view, light, normal = pairs(seed=3)
    white = np.ones((len(view), 3))
    ours = brdf(light, view, normal, white, finish(len(view), alpha=alpha, metalness=1.0), correlated=False)
    mirror = mi.load_dict({"type": "roughconductor", "distribution": "ggx", "alpha": alpha, "material": "none"})
    for i in range(len(view)):
        assert ours[i] == pytest.approx(mitsuba_eval(mirror, view[i], light[i]), rel=REL, abs=1e-7)

    gold = np.array([1.0, 0.766, 0.336])
    tinted = mi.load_dict(
        {
            "type": "roughconductor",
            "distribution": "ggx",
            "alpha": alpha,
            "material": "none",
            "specular_reflectance": {"type": "rgb", "value": gold.tolist()},
        }
    )
    ours = brdf(
        view,
        view,
        normal,
        np.tile(gold, (len(view), 1)),
        finish(len(view), alpha=alpha, metalness=1.0),
        correlated=False,
    )
    for i in range(len(view)):
        assert ours[i] == pytest.approx(mitsuba_eval(tinted, view[i], view[i]), rel=REL)


def test_a_matte_surface_is_mitsubas_diffuse():
    view, light, normal = pairs(seed=4)
    albedo = np.array([0.6, 0.3, 0.1])
    ours = brdf(light, view, normal, np.tile(albedo, (len(view), 1)), finish(len(view), alpha=0.3, specular=0.0))
    diffuse = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo.tolist()}})
    for i in range(len(view)):
        assert ours[i] == pytest.approx(mitsuba_eval(diffuse, view[i], light[i]), rel=REL)


def test_dielectric_fresnel_is_mitsubas():
    for cos in np.linspace(0.02, 1.0, 25):
        for ior in (1.33, 1.5, 2.4):
            assert float(fresnel_dielectric(cos, ior)) == pytest.approx(mi.fresnel(float(cos), ior)[0], rel=REL)


# --- integrals: energy and reciprocity ------------------------------------------------------------
def hemisphere_grid(alpha: float, n_theta: int = 1500, n_phi: int = 720):
    """Directions and solid-angle weights over the upper hemisphere, dense near the pole.

    θ = arctan(α·tan t) for t on a Gauss–Legendre grid: GGX's mass, α wide about the pole,
    is then spread over the whole grid.
    """
    t, wt = np.polynomial.legendre.leggauss(n_theta)
    t = 0.25 * math.pi * (t + 1.0)
    wt = 0.25 * math.pi * wt
    theta = np.arctan(alpha * np.tan(t))
    dtheta = alpha / np.cos(t) ** 2 / (1.0 + (alpha * np.tan(t)) ** 2)
    phi = (np.arange(n_phi) + 0.5) * 2.0 * math.pi / n_phi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    weight = (wt * dtheta * np.sin(theta))[:, None] * np.full(n_phi, 2.0 * math.pi / n_phi)[None, :]
    dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1).reshape(-1, 3)
    return dirs, weight.ravel()


@pytest.mark.parametrize("alpha", ALPHAS)
def test_white_furnace_of_the_distribution_and_of_the_masking(alpha):
    m, weight = hemisphere_grid(alpha)
    d = ggx_distribution(m[:, 2], alpha)
    assert np.sum(d * m[:, 2] * weight) == pytest.approx(1.0, abs=1e-4)  # projected area: 1
    for theta_v in (0.0, 40.0, 75.0):
        v = np.array([math.sin(math.radians(theta_v)), 0.0, math.cos(math.radians(theta_v))])
        visible = np.clip(m @ v, 0.0, None)
        seen = np.sum(smith_masking(v[2], alpha) * visible * d * weight)
        assert seen == pytest.approx(v[2], rel=1e-3)  # the visible facets project to cos θ_v


@pytest.mark.parametrize("alpha", ALPHAS)
def test_the_directional_albedo_of_a_white_mirror_lobe_is_at_most_one(alpha):
    # ∫ f cos θ_l dω_l with F = 1, written over half vectors (dω_l = 4 (v·h) dω_h). Without
    # masking, at normal incidence, it is the share of D·cos θ_h within 45° of the normal
    # (beyond, the light would come from below the horizon): tan²45°/(α² + tan²45°).
    h, weight = hemisphere_grid(alpha)
    for theta_v in (0.0, 45.0, 70.0):
        v = np.array([math.sin(math.radians(theta_v)), 0.0, math.cos(math.radians(theta_v))])
        vh = h @ v
        light = 2.0 * vh[:, None] * h - v
        ok = (vh > 0) & (light[:, 2] > 1e-9)
        lobe = ggx_distribution(h[ok, 2], alpha) * vh[ok] / v[2] * weight[ok]
        unmasked = float(np.sum(lobe))
        albedo = {
            correlated: float(np.sum(lobe * smith_masking_shadowing(light[ok, 2], v[2], alpha, correlated=correlated)))
            for correlated in (True, False)
        }
        assert albedo[True] < unmasked and albedo[True] <= 1.0  # unmasked, 1/cos θ_v can pass 1
        if theta_v == 0.0:
            assert unmasked == pytest.approx(1.0 / (1.0 + alpha**2), rel=3e-3)  # a kink at 45°: quadrature
            # Λ(v) = 0 looking straight down: the two forms of G₂ are the same.
            assert albedo[True] == pytest.approx(albedo[False], rel=1e-12)
        else:  # the separable form counts the shadowing twice where heights correlate them
            assert albedo[False] < albedo[True]


def test_the_brdf_is_reciprocal():
    view, light, normal = pairs(seed=5, count=200)
    rng = np.random.default_rng(6)
    count = len(view)
    mixed = Finish(
        roughness=rng.uniform(0.02, 1.0, count),
        specular=rng.uniform(0.0, 1.0, count),
        ior=rng.uniform(1.2, 2.5, count),
        metalness=rng.uniform(0.0, 1.0, count),
    )
    albedo = rng.uniform(0.0, 1.0, (count, 3))
    forward = brdf(light, view, normal, albedo, mixed)
    backward = brdf(view, light, normal, albedo, mixed)
    np.testing.assert_allclose(forward, backward, rtol=1e-12)
    assert np.all(forward > 0)

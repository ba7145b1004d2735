"""An object's whole reflectance (diffuse, specular, roughness) under three light models, scored
against the simulator's truth.

The light is measured first (the default sweep of the mirrored ball, processed into a light
model: not the truth), then the glazed and gilded vase (``rigs/object-vase-glazed.toml``,
the ``glazed-gilded`` surface: satin glaze α 0.35, glossy glaze and varnish α 0.15, matte
terracotta, gold leaf) is photographed on the ``object-dome`` schedule, noise on, and
``mirrorgonio reflectance`` fits the BRDF per point with each light model. Both runs go
through the daemon's run engine and the simulated devices.

Per light model, over the fitted points and over those whose own highlight pinned their
lobe (confidence "own"):

- diffuse albedo: median and p90 of |ρ − ρ_true|/ρ_true per channel, dielectric regions;
- roughness: median |α − α_true|/α_true on glossy regions;
- specular: median |F0 − F0_true|/F0_true on glossy regions (a dielectric's F0_true is its
  Fresnel reflectance at normal incidence, gold's its tinted F0);
- the share of points whose truth lies within their quoted 1σ (α, and ρ per channel);
- relighting: per held-out light position, the RMS of photograph − rendering over the mean
  radiance, and the median over the positions;
- the time of each step.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.benchmarks.reflectance import OBJECT_RIGS, light_then_object
from drivers.contracts.rig import load_rig
from processing.reflectance.brdf import CONFIDENCE_OWN, BRDFFit
from processing.reflectance.estimate import ReflectanceResult
from sim_devices.brdf import Finish, fresnel_dielectric
from sim_devices.objects import load_surface, surface_finish_at, surface_truth_at

#: The issue's targets (simulated object at the demo resolution, measured light, noise on).
TARGET: dict[str, Any] = {
    "diffuse_median": 0.01,
    "diffuse_p90": 0.03,
    "roughness_median_own": 0.10,
    "specular_median": 0.05,
    "relighting_rms": 0.02,
    "within_sigma": (0.50, 0.85),
    "processing_s": 300.0,
}
WITHIN_SIGMA: tuple[float, float] = TARGET["within_sigma"]
#: Glossy highlights of gold at 25 cm are ~10× the glaze's body: a short exposure holds them.
OBJECT_EXPOSURES_S = (0.25, 2.0, 16.0)


def bench_brdf(
    *,
    object_rig: str = "object-vase-glazed",
    truth: str = "five-gaussians",
    noise: bool = True,
    light_positions: int = 66,
    workdir: str | Path | None = None,
    object_exposures: Sequence[float] = OBJECT_EXPOSURES_S,
) -> dict[str, Any]:
    """Measure the light, photograph the glazed object on its dome, fit the BRDF three ways, score each."""
    rig_path = Path(object_rig)
    if not rig_path.suffix:
        rig_path = OBJECT_RIGS / f"{object_rig}.toml"
    rig = load_rig(rig_path)
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        result, times = light_then_object(rig, truth, noise, light_positions, base, object_exposures)
    if result.materials is None:
        raise RuntimeError(f"{object_rig}: too few light positions for a BRDF fit")
    surface = load_surface(rig.simulation.surface)
    albedo, _ = surface_truth_at(rig, result.points, faces=result.faces, surface=surface)
    finish = surface_finish_at(rig, result.points, faces=result.faces, surface=surface)
    methods = {
        method: score_fit(fit, albedo, finish) | {"relighting": relighting_figures(result, method)}
        for method, fit in result.materials.fits.items()
    }
    measured = methods["measured"]
    return {
        "benchmark": "brdf",
        "object_rig": object_rig,
        "surface": rig.simulation.surface,
        "truth": truth,
        "noise": noise,
        "light_positions": light_positions,
        "object_positions": len(rig.light_poses()),
        "held_out_positions": result.materials.held_out.tolist(),
        "object_exposures_s": list(object_exposures),
        "points_on_object": int(len(result.points)),
        "methods": methods,
        "target": TARGET,
        "meets_target": meets_target(measured, times),
        "times_s": {k: round(v, 1) for k, v in times.items()},
        "reflectance_times_s": result.metadata.get("times_s", {}),
    }


def truth_f0(albedo: np.ndarray, finish: Finish) -> np.ndarray:
    """F0 per point (N, 3): the coat's Fresnel reflectance at normal incidence, or the metal's tint."""
    coat = (finish.specular * fresnel_dielectric(np.ones(len(albedo)), finish.ior))[:, None]
    return np.where(finish.metalness[:, None] > 0, albedo, np.repeat(coat, 3, axis=1))


def _median(values: np.ndarray) -> float | None:
    return round(float(np.median(values)), 5) if values.size else None


def score_fit(fit: BRDFFit, albedo: np.ndarray, finish: Finish) -> dict[str, Any]:
    """The figures of one light model's fit against the truth (see the module's docstring)."""
    fitted = np.isfinite(fit.roughness)
    own = fitted & (fit.confidence == CONFIDENCE_OWN)
    metal = finish.metalness > 0
    dielectric = fitted & ~metal
    glossy = fitted & finish.glossy
    f0_true = truth_f0(albedo, finish)
    out: dict[str, Any] = {
        "points": int(fitted.sum()),
        "own_share": round(float(own.sum() / max(fitted.sum(), 1)), 4),
        "metal_detected": round(float(np.mean(fit.metal[fitted & metal])), 4) if (fitted & metal).any() else None,
        "metal_false": round(float(np.mean(fit.metal[dielectric])), 4) if dielectric.any() else None,
    }
    for name, subset in (("own", own), ("all", fitted)):
        rel_rho = np.abs(fit.diffuse / albedo - 1)[subset & ~metal]
        rel_alpha = np.abs(fit.roughness / finish.roughness - 1)[subset & glossy]
        rel_f0 = np.abs(fit.specular / np.maximum(f0_true, 1e-6) - 1)[subset & glossy]
        within_alpha = (np.abs(fit.roughness - finish.roughness) < fit.sigma_roughness)[subset & glossy]
        within_rho = (np.abs(fit.diffuse - albedo) < fit.sigma_diffuse)[subset & ~metal]
        out[name] = {
            "diffuse_median": [round(float(v), 5) for v in np.median(rel_rho, axis=0)] if rel_rho.size else None,
            "diffuse_p90": [round(float(v), 5) for v in np.percentile(rel_rho, 90, axis=0)] if rel_rho.size else None,
            "roughness_median": _median(rel_alpha),
            "specular_median": _median(rel_f0),
            "within_sigma_roughness_share": round(float(within_alpha.mean()), 4) if within_alpha.size else None,
            "within_sigma_diffuse_share": round(float(within_rho.mean()), 4) if within_rho.size else None,
        }
    return out


def relighting_figures(result: ReflectanceResult, method: str) -> dict[str, Any]:
    """The relighting check of ``method``: overall, per held-out position, and their median."""
    assert result.materials is not None  # the caller checked
    relit = result.materials.relighting.get(method, {})
    per_position = relit.get("per_position", [])
    return {
        "rms_relative": round(relit.get("rms_relative", float("nan")), 5),
        "median_position_rms": round(float(np.median([p["rms_relative"] for p in per_position])), 5)
        if per_position
        else None,
        "per_position": [{k: round(v, 5) if isinstance(v, float) else v for k, v in p.items()} for p in per_position],
    }


def meets_target(measured: dict[str, Any], times: dict[str, float]) -> dict[str, bool]:
    """Which of :data:`TARGET` the measured light model meets."""
    fitted, own = measured["all"], measured["own"]
    low, high = WITHIN_SIGMA
    within = [fitted["within_sigma_roughness_share"], fitted["within_sigma_diffuse_share"]]
    return {
        "diffuse_median": max(fitted["diffuse_median"]) <= TARGET["diffuse_median"],
        "diffuse_p90": max(fitted["diffuse_p90"]) <= TARGET["diffuse_p90"],
        "roughness_median_own": (own["roughness_median"] or 1.0) <= TARGET["roughness_median_own"],
        "specular_median": (own["specular_median"] or 1.0) <= TARGET["specular_median"],
        "relighting_rms": measured["relighting"]["rms_relative"] <= TARGET["relighting_rms"],
        "within_sigma": all(v is not None and low <= v <= high for v in within),
        "processing_s": times.get("reflectance_s", float("inf")) <= TARGET["processing_s"],
    }

"""The simulated truth the demo is scored against, and the light model the worker wrote scored.

The light model is scored as ``mirrorgonio bench accuracy`` scores it:
``RMS(I_fit − I_true) / max(I_true)`` per source over the θ range its samples cover
(:func:`acquisition.benchmarks.scoring.score_fit`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.benchmarks.scoring import score_fit
from drivers.contracts.rig import Rig, load_rig
from processing import LightModel
from sim_devices.lights import LIGHTS_DIR, TruthLight, load_truth


@dataclass
class SourceAccuracy:
    """One truth emitter's score: ``RMS(I_fit − I_true) / max(I_true)`` over the θ covered."""

    name: str
    rms_rel_error: float
    theta_min_deg: float
    theta_max_deg: float
    samples: int
    #: How far the source it was scored against lies from the truth's emitter (0 when the
    #: worker was given the truth's layout).
    offset_m: float = 0.0


def truth_and_layout(rig_path: Path) -> tuple[Rig, TruthLight, Path]:
    """The rig's simulated truth light and its TOML file (which also serves as the source layout)."""
    rig = load_rig(rig_path)
    name = rig.simulation.truth
    path = Path(name) if Path(name).suffix else LIGHTS_DIR / f"{name}.toml"
    return rig, load_truth(name), path.resolve()


def score_light_model(light_model: Path, truth: TruthLight) -> list[SourceAccuracy]:
    """Each truth emitter against the fitted source of the same name (else the nearest one),
    scored as ``mirrorgonio bench accuracy`` does, over the θ its samples cover."""
    model = LightModel.load(light_model)
    by_name = {s.name: s for s in model.sources}
    scores = []
    for emitter in truth.emitters:
        source = by_name.get(emitter.name)
        if source is None:
            source = min(model.sources, key=lambda s: math.dist(s.centre_m, emitter.centre_m))
        offset = math.dist(source.centre_m, emitter.centre_m)
        theta = np.asarray(source.samples.get("theta", []), dtype=float)
        theta = theta[np.isfinite(theta)]
        if theta.size == 0:
            scores.append(SourceAccuracy(emitter.name, float("nan"), float("nan"), float("nan"), 0, offset))
            continue
        error, lo, hi = score_fit(source.fit, emitter, theta)
        scores.append(SourceAccuracy(emitter.name, error, lo, hi, int(theta.size), offset))
    return scores


def aperture_used(light_model: Path) -> str:
    """The camera's aperture the light model's sources were estimated with, in words: fitted to
    the data (the worker's default when it searches for the sources) or the rig's."""
    aperture = LightModel.load(light_model).provenance.get("aperture_m", "")
    if isinstance(aperture, dict) and aperture.get("fitted_m") is not None:
        return (
            f"{1e3 * aperture['fitted_m']:.4g} mm, fitted to the data (the rig says "
            f"{1e3 * aperture['described_m']:.4g} mm)"
        )
    return str(aperture)

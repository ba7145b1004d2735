"""Ground-truth light sources for the simulation, defined in TOML.

A truth is a set of emitting discs on the light plane (z = 0 of the light frame, light
leaving towards +z). Each disc has a uniform radiance over its area whose direction
dependence follows its radiant intensity model: ``L(θ, φ) = I(θ, φ) / (cos θ · π r²)``,
so the disc seen from afar is a point source of intensity ``I(θ, φ)``. A Lambertian disc
is given by its radiance directly. Shipped truths live in ``sim_devices/lights/``; any
other file path works too, so new truths need no code.

An emitter's colour is its ``spectrum``: its camera RGB relative to an equal-energy
spectrum (``(1, 1, 1)`` is flat), or ``cct_k``: a blackbody of that temperature, whose
camera RGB the camera's channel sensitivities give (:meth:`TruthLight.seen_by`), so that a
measurement's chromaticity and CCT can be checked against a known one.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal, Self

import numpy as np
from numpy.typing import ArrayLike
from pydantic import Field, PositiveFloat, model_validator

from drivers.config_files import ConfigModel, load_model
from drivers.contracts.rig import Camera

LIGHTS_DIR = Path(__file__).resolve().parent / "lights"


class TruthError(ValueError):
    """An unreadable or impossible truth file (one line: file, field, cause)."""


class GaussianIntensity(ConfigModel):
    """``I = peak · exp(-θ² / 2σ²)``: rotationally symmetric, as in the reference simulation."""

    model: Literal["gaussian"] = "gaussian"
    peak_w_sr: PositiveFloat = 1.0
    sigma_deg: PositiveFloat = 20.0

    def __call__(self, theta: np.ndarray, phi: ArrayLike) -> np.ndarray:
        s = math.radians(self.sigma_deg)
        return self.peak_w_sr * np.exp(-0.5 * (theta / s) ** 2)


class CosinePowerIntensity(ConfigModel):
    """``I = peak · cos^μ θ``: the usual model of an LED."""

    model: Literal["cos-power"] = "cos-power"
    peak_w_sr: PositiveFloat = 1.0
    mu: PositiveFloat = 3.0

    def __call__(self, theta: np.ndarray, phi: ArrayLike) -> np.ndarray:
        return self.peak_w_sr * np.clip(np.cos(theta), 0.0, None) ** self.mu


class AnisotropicIntensity(ConfigModel):
    """An elliptical Gaussian lobe: widths ``sigma_major`` along azimuth ``azimuth_deg``."""

    model: Literal["anisotropic-gaussian"] = "anisotropic-gaussian"
    peak_w_sr: PositiveFloat = 1.0
    sigma_major_deg: PositiveFloat = 30.0
    sigma_minor_deg: PositiveFloat = 12.0
    azimuth_deg: float = 0.0

    def __call__(self, theta: np.ndarray, phi: ArrayLike) -> np.ndarray:
        a = np.asarray(phi) - math.radians(self.azimuth_deg)
        sm, sn = math.radians(self.sigma_major_deg), math.radians(self.sigma_minor_deg)
        return self.peak_w_sr * np.exp(-0.5 * theta**2 * (np.cos(a) ** 2 / sm**2 + np.sin(a) ** 2 / sn**2))


class LambertianRadiance(ConfigModel):
    """A uniform Lambertian emitter of radiance ``radiance`` (``I = L · cos θ · area``)."""

    model: Literal["lambertian"] = "lambertian"
    radiance_w_sr_m2: PositiveFloat = 1.0


Intensity = Annotated[
    GaussianIntensity | CosinePowerIntensity | AnisotropicIntensity | LambertianRadiance,
    Field(discriminator="model"),
]


class Emitter(ConfigModel):
    """One emitting disc on the light plane."""

    name: str = ""
    centre_m: tuple[float, float] = (0.0, 0.0)
    radius_m: PositiveFloat = 0.5e-3
    spectrum: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cct_k: Annotated[float, Field(ge=1000.0, le=25000.0)] | None = None
    intensity: Intensity = GaussianIntensity()

    @model_validator(mode="after")
    def _one_colour(self) -> Self:
        if self.cct_k is not None and "spectrum" in self.model_fields_set:
            raise ValueError("give spectrum (camera RGB) or cct_k (a blackbody), not both")
        return self

    @property
    def area_m2(self) -> float:
        return math.pi * self.radius_m**2

    def radiance(self, theta: ArrayLike, phi: ArrayLike) -> np.ndarray:
        """Radiance leaving the disc (any point on it) in direction (θ, φ)."""
        theta = np.asarray(theta, dtype=float)
        if isinstance(self.intensity, LambertianRadiance):
            return np.where(theta < math.pi / 2, self.intensity.radiance_w_sr_m2, 0.0)
        cos_t = np.cos(theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            value = self.intensity(theta, phi) / (np.maximum(cos_t, 1e-12) * self.area_m2)
        return np.where(cos_t > 0.0, value, 0.0)

    def intensity_w_sr(self, theta: ArrayLike, phi: ArrayLike = 0.0) -> np.ndarray:
        """Radiant intensity of the whole disc: the truth a fit is compared with."""
        theta = np.asarray(theta, dtype=float)
        if isinstance(self.intensity, LambertianRadiance):
            return self.intensity.radiance_w_sr_m2 * np.clip(np.cos(theta), 0.0, None) * self.area_m2
        return self.intensity(theta, phi)

    def luminous_intensity_cd(self, theta: ArrayLike, phi: ArrayLike, camera: Camera) -> np.ndarray:
        """Luminous intensity of the whole disc (cd), through the CIE observer: the truth of an
        absolute measurement (:func:`sim_devices.colour.candela_per_unit`). Needs ``cct_k``:
        a camera RGB alone defines no spectrum."""
        if self.cct_k is None:
            raise TruthError(f"emitter {self.name}: a luminous intensity needs cct_k (a spectrum), not camera RGB")
        from sim_devices.colour import candela_per_unit  # noqa: PLC0415 - colour-science is heavy

        return candela_per_unit(self.cct_k, camera) * self.intensity_w_sr(theta, phi)


class TruthLight(ConfigModel):
    """A ground-truth light: the emitters on its plane."""

    name: str = "truth"
    description: str = ""
    emitters: list[Emitter] = Field(min_length=1)

    def seen_by(self, camera: Camera) -> TruthLight:
        """The light with every ``cct_k`` emitter's ``spectrum`` set to the blackbody's camera RGB
        (mean 1) through ``camera``'s channels (:func:`sim_devices.colour.blackbody_rgb`); the
        light itself where no emitter gives a temperature."""
        if all(e.cct_k is None for e in self.emitters):
            return self
        from sim_devices.colour import blackbody_rgb  # noqa: PLC0415 - colour-science is heavy

        emitters = [
            e if e.cct_k is None else e.model_copy(update={"spectrum": blackbody_rgb(e.cct_k, camera)})
            for e in self.emitters
        ]
        return self.model_copy(update={"emitters": emitters})


def load_truth(name_or_path: str | Path) -> TruthLight:
    """Load a truth by shipped name (``five-gaussians``) or by TOML path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = LIGHTS_DIR / f"{name_or_path}.toml"
        if not path.exists():
            shipped = ", ".join(sorted(p.stem for p in LIGHTS_DIR.glob("*.toml")))
            raise TruthError(f"{name_or_path}: no such truth light (shipped: {shipped})")
    return load_model(path, TruthLight, "truth file", TruthError)

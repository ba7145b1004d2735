"""The three light models an object's irradiance is computed with: collimated, isotropic point, measured."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from drivers.pose import Pose
from processing.lightmodel import LightModel
from processing.reflectance.codes import ReflectanceError

log = logging.getLogger("mirrorgonio.processing")


def to_rig(pose: Pose, uv: tuple[float, float]) -> np.ndarray:
    """A point ``(u, v, 0)`` of the light plane in the rig frame."""
    u, v = uv
    return pose.position + pose.rotation @ np.array([u, v, 0.0])


def light_centre(light_model: LightModel) -> tuple[tuple[float, float], float]:
    """The light's isotropic point on its plane and its total on-axis intensity.

    Returns
    -------
    (u, v) : tuple of float
        The centroid of the sources weighted by their on-axis intensity ``I_s(0)`` (the
        plain centroid if every ``I_s(0)`` is 0), metres in the light frame.
    I0 : float
        ``Σ_s I_s(0)``, the light's on-axis intensity in the model's units.
    """
    shares, total = light_model.on_axis_shares()
    centres = np.array([s.centre_m for s in light_model.sources], dtype=float)
    u, v = (shares[:, None] * centres).sum(axis=0)
    return (float(u), float(v)), total


@dataclass
class MeasuredLight:
    """The measured near-field model at one light pose (``LightModel.irradiance``)."""

    model: LightModel
    pose: Pose

    @classmethod
    def from_model(cls, light_model: LightModel, pose: Pose, object_centre: ArrayLike | None = None) -> MeasuredLight:
        return cls(light_model, pose)

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """``E(r, n) = Σ_s I_s(θ_s, φ_s)·max(0, n·ω_s)/|r − p_s|²``, rig-frame inputs."""
        rot, origin = self.pose.rotation, self.pose.position
        local = (np.asarray(points, float) - origin) @ rot
        return self.model.irradiance(local, np.asarray(normals, float) @ rot)

    def irradiance_and_tint(self, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`irradiance`, and each channel's share of it (N, 3): the sources' colours
        mixed as they light each point; None for a grey light (every channel the same).
        One pass over the sources either way."""
        if all(s.colour == (1.0, 1.0, 1.0) for s in self.model.sources):
            return self.irradiance(points, normals), None
        rot, origin = self.pose.rotation, self.pose.position
        local = (np.asarray(points, float) - origin) @ rot
        rgb = self.model.irradiance_rgb(local, np.asarray(normals, float) @ rot)
        grey = rgb.mean(axis=1)  # the channel mean is the irradiance (colours have mean 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            return grey, np.where(grey[:, None] > 0, rgb / grey[:, None], 1.0)

    def describe(self) -> dict[str, Any]:
        return {"sources": len(self.model.sources)}


def _uniform_tint(colour: np.ndarray, n: int) -> np.ndarray | None:
    """One light colour for every point (N, 3); None when it is grey."""
    if np.allclose(colour, 1.0, rtol=0, atol=1e-12):
        return None
    return np.broadcast_to(np.asarray(colour, float), (n, 3))


@dataclass
class IsotropicPointLight:
    """One point of intensity ``I₀`` in every direction: ``E = I₀·max(0, n·ω)/d²``."""

    position: np.ndarray
    intensity: float
    colour: np.ndarray = field(default_factory=lambda: np.ones(3))  # the whole light's (LightModel.colour)

    @classmethod
    def from_model(
        cls, light_model: LightModel, pose: Pose, object_centre: ArrayLike | None = None
    ) -> IsotropicPointLight:
        uv, i0 = light_centre(light_model)
        return cls(to_rig(pose, uv), i0, light_model.colour())

    def irradiance_and_tint(self, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        return self.irradiance(points, normals), _uniform_tint(self.colour, len(points))

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        d = self.position - np.asarray(points, float)
        dist2 = np.einsum("ij,ij->i", d, d)
        cos_in = np.einsum("ij,ij->i", np.asarray(normals, float), d) / np.sqrt(dist2)
        return self.intensity * np.maximum(cos_in, 0.0) / dist2

    def describe(self) -> dict[str, Any]:
        return {"point_m": self.position.tolist(), "I0": self.intensity}


@dataclass
class CollimatedLight:
    """One direction and one irradiance for the whole object: ``E = E₀·max(0, n·ω₀)``.

    ``ω₀`` points from the object's centre to the light's isotropic point at distance
    ``d₀``, and ``E₀ = I₀/d₀²``.
    """

    direction: np.ndarray
    irradiance_0: float
    distance: float
    colour: np.ndarray = field(default_factory=lambda: np.ones(3))  # the whole light's (LightModel.colour)

    @classmethod
    def from_model(cls, light_model: LightModel, pose: Pose, object_centre: ArrayLike | None = None) -> CollimatedLight:
        if object_centre is None:
            raise ReflectanceError("collimated light: needs the object's centre")
        uv, i0 = light_centre(light_model)
        towards = to_rig(pose, uv) - np.asarray(object_centre, float)
        d0 = float(np.linalg.norm(towards))
        if not d0 > 0:
            raise ReflectanceError("collimated light: the light sits at the object's centre")
        return cls(towards / d0, i0 / d0**2, d0, light_model.colour())

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        return self.irradiance_0 * np.maximum(np.asarray(normals, float) @ self.direction, 0.0)

    def irradiance_and_tint(self, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        return self.irradiance(points, normals), _uniform_tint(self.colour, len(points))

    def describe(self) -> dict[str, Any]:
        return {"direction": self.direction.tolist(), "E0": self.irradiance_0, "distance_m": self.distance}


class LightAtPose(Protocol):
    """A light model at one light pose (:data:`LIGHT_MODELS`)."""

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray: ...

    def irradiance_and_tint(self, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]: ...

    def describe(self) -> dict[str, Any]: ...


#: The light models by name: ``factory(light_model, light_pose, object_centre)`` → an object
#: whose ``irradiance(points, normals)`` takes rig-frame arrays (N, 3), and whose
#: ``irradiance_and_tint(points, normals)`` gives it with each channel's share of it (N, 3),
#: or None for a grey light.
LIGHT_MODELS: dict[str, Callable[[LightModel, Pose, ArrayLike | None], LightAtPose]] = {
    "collimated": CollimatedLight.from_model,
    "isotropic": IsotropicPointLight.from_model,
    "measured": MeasuredLight.from_model,
}

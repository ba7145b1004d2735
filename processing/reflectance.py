"""Diffuse reflectance of an object lit from close by, under three light models.

``measurement.md``, "Diffuse reflectance of an object lit from close by": an object of
known shape (a mesh registered to the camera) is photographed lit by the measured light
from several positions (the reference experiment: 30 cm away, 10° to 50° in 10° steps).
For a surface point ``r`` with normal ``n`` and observed radiance ``L_o``, a Lambertian
surface has ``ρ = π·L_o / E(r, n)``. The irradiance ``E`` comes from one of three light
models (:data:`LIGHT_MODELS`):

``collimated``
    One direction ``ω₀`` (from the object's centre to the light) and one irradiance
    ``E₀ = I₀/d₀²`` for the whole object: ``E = E₀·max(0, n·ω₀)``.
``isotropic``
    A point of the same intensity ``I₀`` in every direction: ``E = I₀·max(0, n·ω)/d²``.
``measured``
    The fitted near-field model of the light run (:class:`~processing.lightmodel.LightModel`):
    ``E(r, n) = Σ_s I_s(θ_s, φ_s)·max(0, n·ω_s)/|r − p_s|²``.

``I₀ = Σ_s I_s(0)`` is the measured light's total on-axis intensity — what a laboratory
gets from a photometer on the light's axis and the isotropy assumption — and the point the
isotropic and collimated models use is the **intensity-weighted centroid of the sources**
on the light plane (weights ``I_s(0)``), placed in the rig frame by the light's pose.

What one pixel measures (``docs/rig.md``, the simulated camera's radiometry): a pixel's
rate is ``k·⟨L_o·cos⁴β⟩`` with ``k`` the camera's ``sensitivity_e_per_s`` and ``β`` the
chief ray's angle from the optical axis, so ``L_o = rate / (k·cos⁴β)``. The light model is
in the same ``k``-radiometry (its intensities come from the same kind of rates), so ``ρ``
comes out absolute.

The estimate works on superpixels (the 2×2 CFA tiles, :func:`processing.hdr.superpixels`):
the chief ray of superpixel ``(i, j)`` leaves the camera centre through the full-resolution
pixel coordinate ``(2j + 0.5, 2i + 0.5)`` (pixel centres at integer coordinates, as in
:mod:`processing.trace`), and meets the mesh (trimesh ray casting, Embree when installed)
at a point with a **flat face normal** turned towards the camera. Each (light, pixel)
sample is then kept or excluded with a code (:data:`SAMPLE_CODES`), each pixel gets a
reason code (:data:`PIXEL_CODES`), and

    ρ_c = π · Σ_j L_jc·E_j / Σ_j E_j²

is the least-squares solution over the usable lights ``j`` — the same samples for all three
methods, so that they are compared on equal points. On an object of uniform albedo the
measured model gives a uniform ρ where the other two show the fall-off towards the object's
top and bottom of the reference paper's Fig. 11 (the near-field light / mirror-ball
goniophotometer paper ``measurement.md`` calls "the reference paper").

Entry points: :func:`estimate_reflectance` (arrays in, arrays out) and
:func:`reflectance_from_run` (a run file in, the files of ``docs/reflectance.md`` out).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from drivers.pose import Pose

__all__ = [
    "LIGHT_MODELS",
    "METHODS",
    "PIXEL_CODES",
    "SAMPLE_CODES",
    "CollimatedLight",
    "IsotropicPointLight",
    "MeasuredLight",
    "ReflectanceError",
    "ReflectanceResult",
    "ReflectanceSettings",
    "estimate_reflectance",
    "find_light_model",
    "load_mesh",
    "reflectance_from_run",
    "reflectance_profiles",
    "uv_texture",
    "write_outputs",
]

log = logging.getLogger("mirrorgonio.processing")
METHODS = ("collimated", "isotropic", "measured")


class ReflectanceError(ValueError):
    """Input the reflectance estimate cannot work with (one line naming the file and the cause)."""


# --- reason codes --------------------------------------------------------------------------------------
# Per (light, pixel) sample; the first that applies, in this order.
SAMPLE_USED = 0
SAMPLE_PIXEL_EXCLUDED = 1
SAMPLE_HOUSING = 2
SAMPLE_GRAZING = 3
SAMPLE_SHADOW = 4
SAMPLE_SATURATED = 5
SAMPLE_NO_IRRADIANCE = 6
SAMPLE_SPECULAR_GEOMETRY = 7
SAMPLE_SPECULAR_OUTLIER = 8
SAMPLE_CODES = {
    SAMPLE_USED: "used",
    SAMPLE_PIXEL_EXCLUDED: "pixel excluded (background, edge or grazing view)",
    SAMPLE_HOUSING: "the light's housing hides the point from the camera",
    SAMPLE_GRAZING: "grazing incidence (or the surface faces away from the light)",
    SAMPLE_SHADOW: "cast shadow (a source is hidden), or within the shadow margin",
    SAMPLE_SATURATED: "saturated in every exposure, or no HDR value",
    SAMPLE_NO_IRRADIANCE: "a light model gives no irradiance (e.g. behind the light plane)",
    SAMPLE_SPECULAR_GEOMETRY: "specular direction: the half vector lies within the specular angle of the normal",
    SAMPLE_SPECULAR_OUTLIER: "specular outlier: radiance far above the other lights' fit",
}

# Per pixel (superpixel).
PIXEL_VALID = 0
PIXEL_BACKGROUND = 1
PIXEL_EDGE = 2
PIXEL_GRAZING_VIEW = 3
PIXEL_FEW_HOUSING = 4
PIXEL_FEW_GRAZING = 5
PIXEL_FEW_SHADOW = 6
PIXEL_FEW_SATURATED = 7
PIXEL_FEW_NO_IRRADIANCE = 8
PIXEL_FEW_SPECULAR = 9
PIXEL_CODES = {
    PIXEL_VALID: "valid",
    PIXEL_BACKGROUND: "background: the chief ray misses the mesh",
    PIXEL_EDGE: "edge: near a silhouette or a depth discontinuity (mixed pixels)",
    PIXEL_GRAZING_VIEW: "grazing view",
    PIXEL_FEW_HOUSING: "too few lights: the light's housing hides the point",
    PIXEL_FEW_GRAZING: "too few lights: grazing incidence",
    PIXEL_FEW_SHADOW: "too few lights: cast shadows",
    PIXEL_FEW_SATURATED: "too few lights: saturated or no HDR value",
    PIXEL_FEW_NO_IRRADIANCE: "too few lights: no irradiance",
    PIXEL_FEW_SPECULAR: "too few lights: specular highlights",
}
PIXEL_SHORT = {
    0: "valid",
    1: "background",
    2: "edge",
    3: "grazing-view",
    4: "few-lights-housing",
    5: "few-lights-grazing",
    6: "few-lights-shadow",
    7: "few-lights-saturated",
    8: "few-lights-no-irradiance",
    9: "few-lights-specular",
}
SAMPLE_SHORT = {
    0: "used",
    1: "pixel-excluded",
    2: "housing",
    3: "grazing",
    4: "shadow",
    5: "saturated",
    6: "no-irradiance",
    7: "specular-geometry",
    8: "specular-outlier",
}
# The reason map's colours (RGB, 0..255).
PIXEL_COLOURS = {
    0: (200, 200, 200),
    1: (0, 0, 0),
    2: (255, 140, 0),
    3: (148, 103, 189),
    4: (140, 86, 75),
    5: (31, 119, 180),
    6: (44, 60, 160),
    7: (214, 39, 40),
    8: (188, 189, 34),
    9: (23, 190, 207),
}
_FEW_FROM_SAMPLE = {
    SAMPLE_HOUSING: PIXEL_FEW_HOUSING,
    SAMPLE_GRAZING: PIXEL_FEW_GRAZING,
    SAMPLE_SHADOW: PIXEL_FEW_SHADOW,
    SAMPLE_SATURATED: PIXEL_FEW_SATURATED,
    SAMPLE_NO_IRRADIANCE: PIXEL_FEW_NO_IRRADIANCE,
    SAMPLE_SPECULAR_GEOMETRY: PIXEL_FEW_SPECULAR,
    SAMPLE_SPECULAR_OUTLIER: PIXEL_FEW_SPECULAR,
}


@dataclass(frozen=True)
class ReflectanceSettings:
    """The thresholds of the sample selection (``docs/reflectance.md``).

    Attributes
    ----------
    grazing_light_deg : float
        A sample is excluded when the light (its isotropic point) stands less than this
        elevation above the face's plane (``n·ω < sin``).
    grazing_view_deg : float
        A pixel is excluded when the camera sees its face at less than this elevation.
    specular_deg : float
        A sample is excluded when the half vector of the light and view directions lies
        within this angle of the normal (where a specular lobe would peak). 0 disables it.
    outlier : float
        Residual test: with at least 3 usable lights, the light whose radiance exceeds the
        prediction of the other lights' fit by more than this fraction is dropped, one
        light at a time. ``inf`` disables it.
    edge_margin : int
        Superpixels by which silhouettes and depth discontinuities are dilated.
    shadow_margin : int
        Superpixels by which each light's cast shadow is dilated (penumbra, camera blur).
    depth_tolerance : float
        A depth jump between neighbouring pixels larger than this many superpixel
        footprints, that neither pixel's face plane explains, is a discontinuity.
    min_lights : int
        Usable lights a pixel needs (at least 2).
    """

    grazing_light_deg: float = 15.0
    grazing_view_deg: float = 15.0
    specular_deg: float = 15.0
    outlier: float = 0.05
    edge_margin: int = 2
    shadow_margin: int = 1
    depth_tolerance: float = 3.0
    min_lights: int = 2

    def __post_init__(self):
        for name in ("grazing_light_deg", "grazing_view_deg", "specular_deg"):
            value = getattr(self, name)
            if not (0.0 <= value < 90.0):
                raise ReflectanceError(f"{name}: must be in [0, 90) degrees, got {value}")
        if not self.outlier > 0:
            raise ReflectanceError(f"outlier: must be a positive fraction, got {self.outlier}")
        for name in ("edge_margin", "shadow_margin"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 0:
                raise ReflectanceError(f"{name}: must be a whole number >= 0, got {getattr(self, name)}")
        if not self.depth_tolerance > 0:
            raise ReflectanceError(f"depth_tolerance: must be positive, got {self.depth_tolerance}")
        if int(self.min_lights) != self.min_lights or self.min_lights < 2:
            raise ReflectanceError(f"min_lights: must be a whole number >= 2, got {self.min_lights}")


# --- the three light models ----------------------------------------------------------------------------
def _to_rig(pose: Pose, uv) -> np.ndarray:
    """A point ``(u, v, 0)`` of the light plane in the rig frame."""
    u, v = uv
    return pose.position + pose.rotation @ np.array([u, v, 0.0])


def light_centre(light_model) -> tuple[tuple[float, float], float]:
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

    model: object
    pose: Pose

    @classmethod
    def from_model(cls, light_model, pose: Pose, object_centre=None) -> MeasuredLight:
        return cls(light_model, pose)

    def irradiance(self, points, normals) -> np.ndarray:
        """``E(r, n) = Σ_s I_s(θ_s, φ_s)·max(0, n·ω_s)/|r − p_s|²``, rig-frame inputs."""
        rot, origin = self.pose.rotation, self.pose.position
        local = (np.asarray(points, float) - origin) @ rot
        return self.model.irradiance(local, np.asarray(normals, float) @ rot)

    def irradiance_and_tint(self, points, normals) -> tuple[np.ndarray, np.ndarray | None]:
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

    def describe(self) -> dict:
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
    def from_model(cls, light_model, pose: Pose, object_centre=None) -> IsotropicPointLight:
        uv, i0 = light_centre(light_model)
        return cls(_to_rig(pose, uv), i0, light_model.colour())

    def irradiance_and_tint(self, points, normals) -> tuple[np.ndarray, np.ndarray | None]:
        return self.irradiance(points, normals), _uniform_tint(self.colour, len(points))

    def irradiance(self, points, normals) -> np.ndarray:
        d = self.position - np.asarray(points, float)
        dist2 = np.einsum("ij,ij->i", d, d)
        cos_in = np.einsum("ij,ij->i", np.asarray(normals, float), d) / np.sqrt(dist2)
        return self.intensity * np.maximum(cos_in, 0.0) / dist2

    def describe(self) -> dict:
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
    def from_model(cls, light_model, pose: Pose, object_centre=None) -> CollimatedLight:
        if object_centre is None:
            raise ReflectanceError("collimated light: needs the object's centre")
        uv, i0 = light_centre(light_model)
        towards = _to_rig(pose, uv) - np.asarray(object_centre, float)
        d0 = float(np.linalg.norm(towards))
        if not d0 > 0:
            raise ReflectanceError("collimated light: the light sits at the object's centre")
        return cls(towards / d0, i0 / d0**2, d0, light_model.colour())

    def irradiance(self, points, normals) -> np.ndarray:
        return self.irradiance_0 * np.maximum(np.asarray(normals, float) @ self.direction, 0.0)

    def irradiance_and_tint(self, points, normals) -> tuple[np.ndarray, np.ndarray | None]:
        return self.irradiance(points, normals), _uniform_tint(self.colour, len(points))

    def describe(self) -> dict:
        return {"direction": self.direction.tolist(), "E0": self.irradiance_0, "distance_m": self.distance}


#: The light models by name: ``factory(light_model, light_pose, object_centre)`` → an object
#: whose ``irradiance(points, normals)`` takes rig-frame arrays (N, 3), and whose
#: ``irradiance_and_tint(points, normals)`` gives it with each channel's share of it (N, 3),
#: or None for a grey light.
LIGHT_MODELS: dict[str, Callable] = {
    "collimated": CollimatedLight.from_model,
    "isotropic": IsotropicPointLight.from_model,
    "measured": MeasuredLight.from_model,
}


# --- the camera's rays -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class _SuperpixelRays:
    centre: np.ndarray
    directions: np.ndarray  # (H2, W2, 3), rig frame, unit
    cos4: np.ndarray  # (H2, W2)
    angle: float  # a superpixel's angular size at the axis, radians
    optical_axis: np.ndarray

    @classmethod
    def of(cls, camera, shape) -> _SuperpixelRays:
        K = camera.camera_matrix()
        R, t = camera.pose.extrinsics()
        h2, w2 = shape
        rows, cols = np.mgrid[0:h2, 0:w2]
        px = 2.0 * cols + 0.5  # the centre of the 2x2 tile, pixel centres at integers
        py = 2.0 * rows + 0.5
        x = (px - K[0, 2]) / K[0, 0]
        y = (py - K[1, 2]) / K[1, 1]
        in_camera = np.stack([x, y, np.ones_like(x)], axis=-1)
        in_rig = in_camera @ R  # R.T @ d
        directions = in_rig / np.linalg.norm(in_rig, axis=-1, keepdims=True)
        cos4 = aperture_mean_cos4(x, y, camera.aperture_diameter_m / 2.0, camera.sensor_distance_m)
        return cls(-R.T @ np.asarray(t, float), directions, cos4, 2.0 / K[0, 0], R[2].copy())


def aperture_mean_cos4(x, y, aperture_radius: float, sensor_distance: float) -> np.ndarray:
    """``⟨cos⁴β⟩`` over a uniform circular aperture for sensor points at ``(x, y)·f``.

    A pixel gathers light through the whole aperture and each ray's fall-off is the
    ``cos⁴β`` of its own sensor-side segment; with ``q = 1 + x² + y²`` and ``a = R/f``
    (``R`` the aperture's radius, ``f`` the sensor distance), the mean over the disc to
    second order in ``a`` (the next term is ``O(a⁴)``: 1.5e-5 at f/8) is::

        ⟨cos⁴β⟩ = 1/q² + a²·(3(x² + y²)/q⁴ − 1/q³)

    The chief ray's ``1/q²`` alone is 0.4 % high on the axis of an f/8 lens.
    """
    rho2 = x * x + y * y
    q = 1.0 + rho2
    a2 = (aperture_radius / sensor_distance) ** 2
    return 1.0 / q**2 + a2 * (3.0 * rho2 / q**4 - 1.0 / q**3)


def _camera_from(camera):
    """Accept a rig's ``Camera`` or a whole ``Rig``."""
    return getattr(camera, "camera", camera)


def _plane_distance(mesh, faces, origins, directions) -> np.ndarray:
    """Distance along each ray to the plane of the given face (float64, exact for flat faces)."""
    normals = mesh.face_normals[faces]
    v0 = mesh.vertices[mesh.faces[faces, 0]]
    denom = np.einsum("ij,ij->i", normals, directions)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.einsum("ij,ij->i", normals, v0 - origins) / denom


def _first_hits(mesh, origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """First face met by each ray (−1 for none) and the distance to it (``inf`` for none)."""
    faces = np.asarray(mesh.ray.intersects_first(origins, directions), dtype=np.int64)
    dist = np.full(len(origins), np.inf)
    hit = faces >= 0
    if hit.any():
        dist[hit] = _plane_distance(mesh, faces[hit], origins[hit], directions[hit])
    return faces, dist


def _dilate(mask: np.ndarray, iterations: int) -> np.ndarray:
    if iterations <= 0 or not mask.any():
        return mask.copy()
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, structure=np.ones((3, 3), bool), iterations=int(iterations))


def _edge_core(hit, depth, points, normals, directions, centre, angle, tolerance) -> np.ndarray:
    """Silhouettes and depth discontinuities on the superpixel grid (before dilation).

    A hit pixel next to a miss is on a silhouette. Two neighbouring hits are discontinuous
    when the depth of each differs from where its ray meets the other's face plane by more
    than ``tolerance`` superpixel footprints (a smooth surface, even with creases between
    flat faces, is explained by one of the two planes; an occlusion by neither).
    """
    core = np.zeros(hit.shape, bool)
    pad = np.pad(hit, 1, constant_values=True)  # beyond the image is unknown, not background
    neighbour_missing = ~pad[:-2, 1:-1] | ~pad[2:, 1:-1] | ~pad[1:-1, :-2] | ~pad[1:-1, 2:]
    core |= hit & neighbour_missing
    for axis in (0, 1):
        a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        both = hit[a] & hit[b]

        def predicted(src, dst):
            n = normals[src]
            denom = np.einsum("...k,...k->...", n, directions[dst])
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.einsum("...k,...k->...", n, points[src] - centre) / denom

        err_ab = np.abs(depth[b] - predicted(a, b))
        err_ba = np.abs(depth[a] - predicted(b, a))
        err = np.fmin(err_ab, err_ba)
        scale = tolerance * angle * np.fmax(depth[a], depth[b])
        jump = both & ~(err <= scale)  # NaN (a ray parallel to a face) counts as a jump
        core[a] |= jump
        core[b] |= jump
    return core


# --- the estimate ---------------------------------------------------------------------------------------
@dataclass
class ReflectanceResult:
    """What :func:`estimate_reflectance` found.

    Grid arrays are on the superpixel grid ``(H/2, W/2)``; point arrays have one row per
    superpixel whose chief ray meets the mesh (``N`` of them, in row-major order), so that
    ``rho[m][rows, cols] == rho_points[m]``.

    Attributes
    ----------
    methods : tuple of str
        The light models, keys of :data:`LIGHT_MODELS`.
    shape : tuple of int
        ``(H/2, W/2)``.
    rho : dict of str to ndarray (H/2, W/2, 3)
        Albedo per method and channel (R, G, B); NaN where the pixel is not valid.
    reason : ndarray (H/2, W/2) of uint8
        The pixel's reason code (:data:`PIXEL_CODES`; 0 = valid).
    rows, cols : ndarray (N,)
        Superpixel indices of the points on the object.
    points, normals : ndarray (N, 3)
        Hit points and flat face normals (towards the camera), rig frame, metres.
    faces : ndarray (N,)
        Index of the face hit.
    heights : ndarray (N,)
        Height along the object's vertical axis, ``x_object · up``, metres.
    uv : ndarray (N, 2) or None
        The mesh's texture coordinates at the hit points, when it has UVs.
    radiance : ndarray (n_lights, N, 3)
        ``L_o = rate / (k·cos⁴β)`` per light and channel.
    irradiance : dict of str to ndarray (n_lights, N)
        ``E`` per method and light: the channel mean.
    colour : dict of str to ndarray (n_lights, N, 3) or None
        Each channel's share of ``E`` per method, light and point (mean 1: the sources'
        colours as they mix there); None for a grey light. Each channel's irradiance,
        the one ``rho`` divides by, is ``E·colour`` (:meth:`irradiance_rgb`).
    sample_code : ndarray (n_lights, N) of uint8
        Each sample's code (:data:`SAMPLE_CODES`; 0 = used).
    rho_points : dict of str to ndarray (N, 3)
        ``rho`` at the points (NaN where not valid).
    lights : list of dict
        Per light position: its pose and what each model made of it (isotropic point, I₀,
        collimated direction and E₀).
    settings : ReflectanceSettings
        The thresholds used.
    object_centre : ndarray (3,)
        Centre of the mesh's bounding box in the rig frame (the collimated model's origin).
    warnings : list of str
        Things worth knowing that did not stop the estimate.
    outputs : dict of str to Path
        Files written by :func:`write_outputs` (empty until then).
    """

    methods: tuple[str, ...]
    shape: tuple[int, int]
    rho: dict[str, np.ndarray]
    reason: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    heights: np.ndarray
    uv: np.ndarray | None
    radiance: np.ndarray
    irradiance: dict[str, np.ndarray]
    colour: dict[str, np.ndarray | None]
    sample_code: np.ndarray
    rho_points: dict[str, np.ndarray]
    lights: list[dict]
    settings: ReflectanceSettings
    object_centre: np.ndarray
    warnings: list[str] = field(default_factory=list)
    outputs: dict[str, Path] = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)

    def irradiance_rgb(self, method: str) -> np.ndarray:
        """Each channel's irradiance per light and point, (n_lights, N, 3) float32: what
        ``rho[method]`` was solved with, ``ρ_c = π Σ_j L_jc E_jc / Σ_j E_jc²`` over the used
        samples."""
        return _channel_irradiance(self.irradiance[method], self.colour[method]).astype(np.float32)

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: the points with an albedo."""
        return self.reason[self.rows, self.cols] == PIXEL_VALID

    @property
    def lights_used(self) -> np.ndarray:
        """(N,) number of lights each point's albedo was solved from."""
        return (self.sample_code == SAMPLE_USED).sum(axis=0)

    def summary(self) -> dict:
        """Counts per reason and per-method statistics of ρ (the ``reflectance.json`` core).

        ``median`` is per channel; ``cv`` is the standard deviation over the mean and
        ``robust_cv`` 1.4826·MAD over the median, both of the channel mean of ρ over the valid
        points.
        """
        reasons = {PIXEL_SHORT[c]: int((self.reason == c).sum()) for c in PIXEL_CODES}
        considered = self.sample_code != SAMPLE_PIXEL_EXCLUDED
        samples = {
            SAMPLE_SHORT[c]: int(((self.sample_code == c) & considered).sum())
            for c in SAMPLE_CODES
            if c != SAMPLE_PIXEL_EXCLUDED
        }
        valid = self.valid
        methods = {}
        for m in self.methods:
            rho = self.rho_points[m][valid]
            grey = rho.mean(axis=1)
            stats = {"valid_points": int(valid.sum())}
            if grey.size:
                median = float(np.median(grey))
                mean = float(grey.mean())
                stats.update(
                    median=[float(v) for v in np.median(rho, axis=0)],
                    median_mean=median,
                    mean=mean,
                    cv=float(grey.std() / mean) if mean != 0 else float("nan"),
                    robust_cv=float(1.4826 * np.median(np.abs(grey - median)) / median)
                    if median != 0
                    else float("nan"),
                    q25=float(np.percentile(grey, 25)),
                    q75=float(np.percentile(grey, 75)),
                )
            methods[m] = stats
        return {
            "superpixels": list(self.shape),
            "on_object": int(len(self.rows)),
            "valid": int(valid.sum()),
            "lights": len(self.lights),
            "pixel_reasons": reasons,
            "sample_reasons": samples,
            "methods": methods,
            "object_centre_m": self.object_centre.tolist(),
            "light_positions": self.lights,
            "settings": asdict(self.settings),
            "warnings": list(self.warnings),
        }


def _superpixel_any(mask: np.ndarray) -> np.ndarray:
    """(..., H/2, W/2): any of each 2x2 tile's sites set."""
    h, w = mask.shape[-2:]
    m = mask[..., : h - h % 2, : w - w % 2]
    return m.reshape(*m.shape[:-2], h // 2, 2, w // 2, 2).any(axis=(-3, -1))


def estimate_reflectance(
    radiance_rgb,
    saturated,
    camera,
    mesh_rig,
    light_poses,
    light_model,
    *,
    object_pose: Pose | None = None,
    up=(0.0, 1.0, 0.0),
    housing=None,
    settings: ReflectanceSettings | None = None,
    methods=METHODS,
    mesh_name: str = "the mesh",
    progress: Callable[[str, int, int], None] | None = None,
) -> ReflectanceResult:
    """Albedo per pixel under three light models, from one object run's HDR radiance.

    Parameters
    ----------
    radiance_rgb : array_like (n_lights, H/2, W/2, 3)
        Each light position's superpixel rate in e⁻/s (R, G, B; the greens averaged:
        :func:`processing.hdr.superpixels` of the HDR mosaic times the conversion gain).
        Non-finite values are samples without data.
    saturated : array_like (n_lights, H/2, W/2) of bool, or None
        Superpixels with a site saturated in every exposure.
    camera : drivers.contracts.rig.Camera (or a Rig)
        Intrinsics, pose and ``sensitivity_e_per_s`` = k; its sensor is ``(H, W)``.
    mesh_rig : trimesh.Trimesh
        The object in the rig frame, metres (:func:`load_mesh`).
    light_poses : sequence of Pose
        The light's pose (light frame in the rig frame) at each position.
    light_model : LightModel
        The measured light (:class:`processing.lightmodel.LightModel`), whose sources also
        cast the shadows.
    object_pose : Pose, optional
        The object frame in the rig frame (metres), for the heights; the rig frame if None.
    up : sequence of 3 float
        The object's vertical axis in its own frame (``heights = x_object · up``).
    housing : (radius_m, depth_m), optional
        The light's housing (``[light]`` of the rig): samples it hides from the camera are
        excluded.
    settings : ReflectanceSettings, optional
        Thresholds (the defaults of :class:`ReflectanceSettings` when None).
    methods : sequence of str
        Keys of :data:`LIGHT_MODELS`; ``"measured"`` is always computed (the residual test
        uses it).
    mesh_name : str
        How error messages name the mesh.
    progress : callable, optional
        ``progress(stage, done, total)``.

    Returns
    -------
    ReflectanceResult

    Raises
    ------
    ReflectanceError
        Arrays of the wrong shape, fewer than two light positions, a mesh that no camera
        ray meets, or no valid point at all.

    Notes
    -----
    ``L_o = rate/(k·cos⁴β)`` and, for a Lambertian surface, ``ρ = π·L_o/E(r, n)``
    (``measurement.md``, last section); with several lights ``ρ_c = π·Σ_j L_jc E_j / Σ_j E_j²``
    over the usable lights, the same for every method.
    """
    settings = settings or ReflectanceSettings()
    camera = _camera_from(camera)
    methods = tuple(methods)
    unknown = [m for m in methods if m not in LIGHT_MODELS]
    if unknown or not methods:
        raise ReflectanceError(
            f"methods: {unknown[0] if unknown else 'none'!r} is not one of {', '.join(LIGHT_MODELS)}"
        )
    radiance_rgb = np.asarray(radiance_rgb, dtype=np.float64)
    n_lights = len(light_poses)
    expected = (n_lights, camera.height // 2, camera.width // 2, 3)
    if radiance_rgb.shape != expected:
        raise ReflectanceError(f"radiance: expected shape {expected} (lights, H/2, W/2, RGB), got {radiance_rgb.shape}")
    if n_lights < settings.min_lights:
        raise ReflectanceError(f"{n_lights} light position(s): the albedo needs at least {settings.min_lights}")
    shape = expected[1:3]
    sat = np.zeros((n_lights, *shape), bool) if saturated is None else np.asarray(saturated, bool)
    if sat.shape != (n_lights, *shape):
        raise ReflectanceError(f"saturated: expected shape {(n_lights, *shape)}, got {sat.shape}")
    if mesh_rig is None or len(getattr(mesh_rig, "faces", ())) == 0:
        raise ReflectanceError(f"{mesh_name}: the mesh has no faces")

    def report(stage, done, total):
        if progress:
            progress(stage, done, total)

    # Chief rays -> points, flat normals towards the camera.
    rays = _SuperpixelRays.of(camera, shape)
    flat_dirs = rays.directions.reshape(-1, 3)
    origins = np.broadcast_to(rays.centre, flat_dirs.shape)
    report("rays", 0, n_lights + 1)
    faces_all, depth_all = _first_hits(mesh_rig, np.ascontiguousarray(origins), flat_dirs)
    hit_flat = (faces_all >= 0) & np.isfinite(depth_all) & (depth_all > 0)
    if not hit_flat.any():
        centre = mesh_rig.bounds.mean(axis=0)
        raise ReflectanceError(
            f"no camera ray meets {mesh_name} (its centre is at {np.round(centre, 4).tolist()} m "
            f"in the rig frame); check [object] pose and units_m"
        )
    face_normals = np.asarray(mesh_rig.face_normals, dtype=float)
    hit = hit_flat.reshape(shape)
    depth = np.where(hit_flat, depth_all, np.nan).reshape(shape)
    normals_grid = np.zeros((*shape, 3))
    normals_grid.reshape(-1, 3)[hit_flat] = face_normals[faces_all[hit_flat]]
    facing = np.einsum("...k,...k->...", normals_grid, rays.directions)
    normals_grid *= np.where(facing > 0, -1.0, 1.0)[..., None]  # towards the camera
    points_grid = rays.centre + depth[..., None] * rays.directions
    bad_normal = hit & ~(np.linalg.norm(normals_grid, axis=-1) > 0.5)  # a degenerate face
    normals_grid[bad_normal] = -rays.directions[bad_normal]  # any unit vector: these pixels are edges

    core = (
        _edge_core(
            hit, depth, points_grid, normals_grid, rays.directions, rays.centre, rays.angle, settings.depth_tolerance
        )
        | bad_normal
    )
    band = _dilate(core, settings.edge_margin)
    cos_view = -np.einsum("...k,...k->...", normals_grid, rays.directions)
    grazing_view = cos_view < math.sin(math.radians(settings.grazing_view_deg))
    reason = np.full(shape, PIXEL_VALID, np.uint8)
    reason[~hit] = PIXEL_BACKGROUND
    reason[hit & band] = PIXEL_EDGE
    reason[hit & ~band & grazing_view] = PIXEL_GRAZING_VIEW
    pixel_ok = reason == PIXEL_VALID

    rows, cols = np.nonzero(hit)
    points = points_grid[rows, cols]
    normals = normals_grid[rows, cols]
    view = -rays.directions[rows, cols]
    faces = faces_all.reshape(shape)[rows, cols]
    ok = pixel_ok[rows, cols]
    n_points = len(rows)
    k = float(camera.sensitivity_e_per_s)
    L = radiance_rgb[:, rows, cols, :] / (k * rays.cos4[rows, cols][None, :, None])
    object_centre = np.asarray(mesh_rig.bounds, float).mean(axis=0)
    all_methods = tuple(dict.fromkeys((*methods, "measured")))

    codes = np.full((n_lights, n_points), SAMPLE_USED, np.uint8)
    codes[:, ~ok] = SAMPLE_PIXEL_EXCLUDED
    E = {m: np.zeros((n_lights, n_points)) for m in all_methods}
    tints: dict[str, np.ndarray | None] = dict.fromkeys(all_methods)  # (n_lights, n_points, 3), None: grey
    lights = []
    scene = float(np.linalg.norm(np.ptp(mesh_rig.bounds, axis=0)))
    offset = 1e-5 * max(scene, 1e-6)
    uv_c, i0 = light_centre(light_model)
    sin_graze = math.sin(math.radians(settings.grazing_light_deg))
    cos_spec = math.cos(math.radians(settings.specular_deg)) if settings.specular_deg > 0 else 2.0
    for j, pose in enumerate(light_poses):
        report("lights", j + 1, n_lights + 1)
        centre_point = _to_rig(pose, uv_c)
        towards = centre_point - points
        omega = towards / np.linalg.norm(towards, axis=1, keepdims=True)
        cos_in = np.einsum("ij,ij->i", normals, omega)
        models = {m: LIGHT_MODELS[m](light_model, pose, object_centre) for m in all_methods}
        for m, lm in models.items():
            E[m][j], tint = lm.irradiance_and_tint(points, normals)
            if tint is not None:
                if tints[m] is None:
                    tints[m] = np.ones((n_lights, n_points, 3), np.float32)
                tints[m][j] = tint
        lights.append(
            {
                "index": j,
                "position_m": pose.position.tolist(),
                "rotation_rad": [pose.rx, pose.ry, pose.rz],
                "isotropic_point_m": centre_point.tolist(),
                "I0": i0,
                **{f"{m}": lm.describe() for m, lm in models.items() if m != "measured"},
            }
        )
        # Cast shadows: a ray to every source of the measured model.
        lit_side = cos_in > 0
        shadow = np.zeros(n_points, bool)
        if lit_side.any():
            start = points[lit_side] + offset * normals[lit_side]
            for source in light_model.sources:
                to_source = _to_rig(pose, source.centre_m) - start
                dist = np.linalg.norm(to_source, axis=1)
                first, along = _first_hits(mesh_rig, start, to_source / dist[:, None])
                shadow[np.flatnonzero(lit_side)[(first >= 0) & (along > 0) & (along < dist)]] = True
        shadow_grid = np.zeros(shape, bool)
        shadow_grid[rows[shadow], cols[shadow]] = True
        shadow = _dilate(shadow_grid, settings.shadow_margin)[rows, cols] & lit_side
        housing_blocks = np.zeros(n_points, bool)
        if housing is not None and housing[0] > 0:
            from processing.trace import _housing_blocks

            housing_blocks = _housing_blocks(
                np.broadcast_to(rays.centre, points.shape), points, pose, float(housing[0]), float(housing[1])
            )
        no_data = sat[j, rows, cols] | ~np.all(np.isfinite(radiance_rgb[j, rows, cols, :]), axis=1)
        no_irradiance = np.zeros(n_points, bool)
        for m in all_methods:
            no_irradiance |= ~(E[m][j] > 0)
        half = omega + view
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        specular = np.einsum("ij,ij->i", half, normals) > cos_spec
        code = codes[j]
        for mask, value in (
            (housing_blocks, SAMPLE_HOUSING),
            (cos_in < sin_graze, SAMPLE_GRAZING),
            (shadow, SAMPLE_SHADOW),
            (no_data, SAMPLE_SATURATED),
            (no_irradiance, SAMPLE_NO_IRRADIANCE),
            (specular, SAMPLE_SPECULAR_GEOMETRY),
        ):
            code[(code == SAMPLE_USED) & mask] = value

    _drop_outliers(codes, L.mean(axis=2), E["measured"], settings.outlier)

    used = codes == SAMPLE_USED
    count = used.sum(axis=0)
    enough = ok & (count >= settings.min_lights)
    few = ok & ~enough
    if few.any():
        excluded = codes[:, few]
        tallies = np.stack([(excluded == c).sum(axis=0) for c in range(len(SAMPLE_CODES))])
        tallies[SAMPLE_USED] = tallies[SAMPLE_PIXEL_EXCLUDED] = -1
        reason[rows[few], cols[few]] = np.vectorize(_FEW_FROM_SAMPLE.get)(np.argmax(tallies, axis=0)).astype(np.uint8)

    rho_points, rho = {}, {}
    w = used.astype(float)
    for m in methods:
        if tints[m] is None:  # grey: one irradiance for every channel
            num = np.einsum("jn,jnc,jn->nc", w, np.where(used[..., None], L, 0.0), E[m])
            den = np.einsum("jn,jn->n", w, E[m] ** 2)[:, None]
        else:  # each channel's own irradiance: the light's tint is not the surface's
            channel_e = _channel_irradiance(E[m], tints[m])
            num = np.einsum("jn,jnc,jnc->nc", w, np.where(used[..., None], L, 0.0), channel_e)
            den = np.einsum("jn,jnc->nc", w, channel_e**2)
        with np.errstate(divide="ignore", invalid="ignore"):
            values = math.pi * num / den
        values[~enough] = np.nan
        rho_points[m] = values
        grid = np.full((*shape, 3), np.nan)
        grid[rows, cols] = values
        rho[m] = grid
    report("lights", n_lights + 1, n_lights + 1)

    if not enough.any():
        counts = ", ".join(
            f"{PIXEL_SHORT[c]} {int((reason == c).sum())}"
            for c in PIXEL_CODES
            if c not in (PIXEL_VALID, PIXEL_BACKGROUND) and (reason == c).any()
        )
        raise ReflectanceError(
            f"no valid points: {n_points} superpixels on {mesh_name}, all excluded ({counts or 'none'})"
        )

    object_pose = object_pose or Pose(0.0, 0.0, 0.0)
    up = np.asarray(up, float)
    up = up / np.linalg.norm(up)
    heights = ((points - object_pose.position) @ object_pose.rotation) @ up
    uv = _uv_at(mesh_rig, faces, points)
    warnings = []
    extrapolated = _extrapolated_fraction(light_model, light_poses, points[enough])
    if extrapolated > 0.01:
        warnings.append(
            f"{100 * extrapolated:.0f} % of the valid points are lit at angles the light model "
            "extrapolates (outside the θ its samples cover)"
        )
    return ReflectanceResult(
        methods,
        shape,
        rho,
        reason,
        rows,
        cols,
        points,
        normals,
        faces,
        heights,
        uv,
        L,
        {m: E[m] for m in methods},
        {m: tints[m] for m in methods},
        codes,
        rho_points,
        lights,
        settings,
        object_centre,
        warnings,
    )


def _channel_irradiance(grey: np.ndarray, colour: np.ndarray | None) -> np.ndarray:
    """Each channel's irradiance (..., 3) from the channel mean ``grey`` and each channel's
    share of it (None: grey, every channel the same)."""
    return grey[..., None] * colour if colour is not None else np.repeat(grey[..., None], 3, axis=-1)


def _drop_outliers(codes: np.ndarray, luminance: np.ndarray, irradiance: np.ndarray, threshold: float) -> None:
    """The residual test for highlights, in place on ``codes``.

    For every point with at least 3 usable lights, each light's radiance is predicted from
    the least-squares fit of the others (leave-one-out, measured model); the light with the
    largest relative excess is dropped (:data:`SAMPLE_SPECULAR_OUTLIER`) if the excess is
    above ``threshold``, and the test repeats while at least 3 lights remain.
    """
    if not math.isfinite(threshold):
        return
    L = np.where(np.isfinite(luminance), luminance, 0.0)
    E = irradiance
    while True:
        used = codes == SAMPLE_USED
        candidates = used.sum(axis=0) >= 3
        if not candidates.any():
            return
        idx = np.flatnonzero(candidates)
        u, lum, e = used[:, idx], L[:, idx], E[:, idx]
        s_le = np.where(u, lum * e, 0.0).sum(axis=0)
        s_ee = np.where(u, e * e, 0.0).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            rho_others = (s_le[None] - lum * e) / (s_ee[None] - e * e)
            predicted = rho_others * e
            excess = np.where(u & (predicted > 0), lum / predicted - 1.0, -np.inf)
        worst = np.argmax(excess, axis=0)
        value = excess[worst, np.arange(len(idx))]
        drop = value > threshold
        if not drop.any():
            return
        codes[worst[drop], idx[drop]] = SAMPLE_SPECULAR_OUTLIER


def _uv_at(mesh, faces, points) -> np.ndarray | None:
    """The mesh's UV coordinates at hit points (barycentric), or None without UVs."""
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        return None
    import trimesh

    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)
    corners = np.asarray(uv, float)[mesh.faces[faces]]  # (N, 3, 2)
    return np.einsum("nk,nkc->nc", bary, corners)


def _extrapolated_fraction(light_model, light_poses, points) -> float:
    """Share of points that some light sees at a θ outside any source's sampled range."""
    if len(points) == 0:
        return 0.0
    flagged = np.zeros(len(points), bool)
    for pose in light_poses:
        local = (points - pose.position) @ pose.rotation
        for s in light_model.sources:
            d = local - np.array([s.centre_m[0], s.centre_m[1], 0.0])
            theta = np.arccos(np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -1.0, 1.0))
            lo, hi = s.fit.theta_range
            if hi > lo:
                flagged |= (theta < lo - 1e-9) | (theta > hi + 1e-9)
    return float(flagged.mean())


# --- profiles and texture -----------------------------------------------------------------------------------
def reflectance_profiles(result: ReflectanceResult, bins: int = 24, min_points: int = 5) -> dict:
    """ρ along the object's vertical axis: median and interquartile band per height bin.

    The reference paper's Fig. 11: for each method the channel mean of ρ over the valid
    points, binned by height (``x_object · up``).

    Returns
    -------
    dict
        ``{"height_m": centres, "edges_m": edges, "<method>": {"median", "q25", "q75",
        "count"}}``, lists with NaN where a bin holds fewer than ``min_points``.
    """
    valid = result.valid
    h = result.heights[valid]
    if h.size == 0:
        return {"height_m": [], "edges_m": []}
    lo, hi = float(h.min()), float(h.max())
    if hi <= lo:
        hi = lo + 1e-6
    edges = np.linspace(lo, hi, bins + 1)
    which = np.clip(np.digitize(h, edges) - 1, 0, bins - 1)
    out = {"height_m": (0.5 * (edges[:-1] + edges[1:])).tolist(), "edges_m": edges.tolist()}
    for m in result.methods:
        grey = result.rho_points[m][valid].mean(axis=1)
        stats = {"median": [], "q25": [], "q75": [], "count": []}
        for b in range(bins):
            values = grey[which == b]
            stats["count"].append(int(values.size))
            if values.size >= min_points:
                q25, med, q75 = np.percentile(values, [25, 50, 75])
            else:
                q25 = med = q75 = float("nan")
            stats["median"].append(float(med))
            stats["q25"].append(float(q25))
            stats["q75"].append(float(q75))
        out[m] = stats
    return out


def uv_texture(result: ReflectanceResult, method: str, size: int = 1024, fill: int = 2) -> np.ndarray | None:
    """ρ splatted into the mesh's UV space.

    Each valid pixel's ρ goes to the texel its UV falls in (``v`` up, so row 0 is ``v = 1``);
    a texel holds the mean of the pixels that land in it. Where the camera's pixels are
    sparser than the texels, empty texels within ``fill`` texels of filled ones take the
    mean of their filled 3 × 3 neighbours (``fill`` passes); the rest stay NaN.

    Returns
    -------
    ndarray (size, size, 3) or None
        None when the mesh has no UVs.
    """
    if result.uv is None:
        return None
    from scipy.ndimage import uniform_filter

    valid = result.valid & np.all(np.isfinite(result.uv), axis=1)
    uv = result.uv[valid]
    rho = result.rho_points[method][valid]
    u = np.mod(uv[:, 0], 1.0)
    v = np.mod(uv[:, 1], 1.0)
    col = np.clip((u * size).astype(int), 0, size - 1)
    row = np.clip(((1.0 - v) * size).astype(int), 0, size - 1)
    flat = row * size + col
    total = np.zeros((size * size, 3))
    count = np.bincount(flat, minlength=size * size).astype(float)
    for c in range(3):
        total[:, c] = np.bincount(flat, weights=rho[:, c], minlength=size * size)
    with np.errstate(divide="ignore", invalid="ignore"):
        texture = (total / count[:, None]).reshape(size, size, 3)
    for _ in range(max(0, int(fill))):
        known = np.all(np.isfinite(texture), axis=-1)
        if known.all() or not known.any():
            break
        weight = uniform_filter(known.astype(float), size=3, mode="constant")
        summed = np.stack(
            [uniform_filter(np.where(known, texture[..., c], 0.0), size=3, mode="constant") for c in range(3)], axis=-1
        )
        grow = ~known & (weight > 0.5 / 9.0)  # at least one filled neighbour (not round-off)
        texture[grow] = summed[grow] / weight[grow, None]
    return texture


# --- files ------------------------------------------------------------------------------------------------------
def load_mesh(path, units_m: float = 1.0, pose: Pose | None = None):
    """Read a PLY, OBJ or STL mesh with trimesh and place it in the rig frame.

    ``x_rig = R·(units_m·v) + t`` for the pose's rotation ``R`` and position ``t``
    (``[object]`` of the rig, ``docs/rig.md``).

    Raises
    ------
    ReflectanceError
        One line naming the file: missing, unreadable, or without faces.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ReflectanceError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # noqa: BLE001 - trimesh's loaders raise anything
        raise ReflectanceError(
            f"{path}: cannot read the mesh ({type(exc).__name__}: {' '.join(str(exc).split())})"
        ) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ReflectanceError(f"{path}: cannot read the mesh (no triangles in it)")
    mesh = mesh.copy()
    if units_m != 1.0:
        mesh.apply_scale(float(units_m))
    if pose is not None:
        mesh.apply_transform(pose.matrix())
    return mesh


def find_light_model(light) -> Path:
    """The ``.light.json`` a ``--light`` argument means.

    ``light`` may be the light-model file itself, the light run's results folder (holding
    one ``*.light.json``), its ``RUN.results.h5`` or its run file ``RUN.h5`` (the model is
    ``RUN.light.json`` beside it).
    """
    path = Path(light)
    if path.is_dir():
        found = sorted(path.glob("*.light.json"))
        if len(found) == 1:
            return found[0]
        if not found:
            raise ReflectanceError(f"{path}: no *.light.json light model in this folder (process the light run first)")
        raise ReflectanceError(
            f"{path}: {len(found)} light models in this folder ({', '.join(p.name for p in found)}): give the file"
        )
    if path.name.endswith(".json"):
        if not path.is_file():
            raise ReflectanceError(f"{path}: light model not found")
        return path
    if path.suffix == ".h5":
        stem = path.name[: -len(".results.h5")] if path.name.endswith(".results.h5") else path.stem
        candidate = path.with_name(f"{stem}.light.json")
        if candidate.is_file():
            return candidate
        raise ReflectanceError(
            f"{path}: no light model {candidate.name} beside it (process the light run with the sources step)"
        )
    raise ReflectanceError(f"{path}: not a light model, a results folder or a results file")


def _light_section(rig_like) -> dict | None:
    """The ``[light]`` of a rig (a Rig or its dict) as comparable numbers, or None."""
    from drivers.contracts.rig import Light

    if rig_like is None:
        return None
    section = rig_like.get("light", {}) if isinstance(rig_like, dict) else rig_like.light
    try:
        light = section if isinstance(section, Light) else Light.model_validate(section)
    except ValueError:
        return None
    return {
        "light_to_tool.position_m": tuple(light.light_to_tool.position_m),
        "light_to_tool.rotation_deg": tuple(light.light_to_tool.rotation_deg),
        "housing_radius_m": light.housing_radius_m,
        "housing_depth_m": light.housing_depth_m,
    }


def _light_run_rig(light_model):
    """The light run's rig: ``provenance["rig"]`` when it is the rig itself, else the rig
    stored in the run file the provenance names (None when neither is at hand)."""
    for key in ("rig_description", "rig"):
        rig = light_model.provenance.get(key)
        if isinstance(rig, dict):
            return rig
    run_file = light_model.provenance.get("run_file")
    if run_file and Path(run_file).is_file():
        from drivers.contracts.runfile import RunFile, RunFileError

        try:
            with RunFile.open(run_file) as run:
                return run.header.rig
        except RunFileError:
            return None
    return None


def check_light_frame(light_model, light_path, rig, run_path) -> str | None:
    """Refuse a light model measured on a rig whose ``[light]`` differs from the object run's.

    The light frame is the arm's tool frame composed with ``light_to_tool``; a model made
    with another mounting (or another housing) does not describe this run's light.

    Returns
    -------
    str or None
        A warning when the light run's rig is not known (the check could not be made).
    """
    theirs = _light_run_rig(light_model)
    if theirs is None:
        return (
            f"{light_path}: the light model does not record its rig's [light] section and its run file is not at "
            "hand: the light frame could not be checked"
        )
    a, b = _light_section(theirs), _light_section(rig)
    if a is None or b is None:
        return f"{light_path}: the light run's [light] section is unreadable: the light frame could not be checked"
    differs = [k for k in a if not np.allclose(np.atleast_1d(a[k]), np.atleast_1d(b[k]), rtol=0.0, atol=1e-9)]
    if differs:
        name_a = theirs.get("name", "?") if isinstance(theirs, dict) else theirs.name
        key = differs[0]
        raise ReflectanceError(
            f"{light_path}: light results from a different rig: the light run's rig {name_a!r} has [light] "
            f"{key} = {list(np.atleast_1d(a[key]))}, the object run {run_path}'s rig {rig.name!r} has "
            f"{list(np.atleast_1d(b[key]))}: the light frame would not be the same"
        )
    return None


def _write_exr(path: Path, rgb: np.ndarray) -> Path:
    """An RGB float32 OpenEXR that keeps NaN (``processing.images.write_exr`` writes 0 there)."""
    import OpenEXR

    data = np.ascontiguousarray(rgb, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": data}) as exr:
        exr.write(str(path))
    return path


def _write_rgba_png(path: Path, rgba: np.ndarray) -> Path:
    import cv2

    if not cv2.imwrite(str(path), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA)):
        raise OSError(f"{path}: could not write the PNG")
    return path


def _albedo_png(path: Path, rgb: np.ndarray, scale: float) -> Path:
    """ρ/scale, display gamma 1/2.2, transparent where there is no albedo."""
    finite = np.all(np.isfinite(rgb), axis=-1)
    shown = np.clip(np.where(finite[..., None], rgb, 0.0) / scale, 0.0, 1.0) ** (1.0 / 2.2)
    rgba = np.zeros((*rgb.shape[:2], 4), np.uint8)
    rgba[..., :3] = (255.0 * shown + 0.5).astype(np.uint8)
    rgba[..., 3] = np.where(finite, 255, 0)
    return _write_rgba_png(path, rgba)


def _reason_png(path: Path, reason: np.ndarray) -> Path:
    rgba = np.full((*reason.shape, 4), 255, np.uint8)
    for code, colour in PIXEL_COLOURS.items():
        rgba[reason == code, :3] = colour
    return _write_rgba_png(path, rgba)


def write_outputs(
    result: ReflectanceResult, out_dir, *, texture_size: int = 1024, bins: int = 24, metadata: dict | None = None
) -> dict[str, Path]:
    """Write the files of ``docs/reflectance.md`` into ``out_dir``; returns them by name.

    Per method ``albedo-<method>.exr`` (NaN where invalid) and ``.png``; ``reasons.png``;
    ``texture-<method>.exr`` and ``.png`` when the mesh has UVs; ``profiles.png``;
    ``reflectance.h5`` (the per-point data); ``reflectance.json`` (the summary); and
    ``report.html``.
    """
    import h5py

    from processing.report import reflectance_profiles_figure, write_reflectance_report

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    finite = [v[np.isfinite(v)] for v in result.rho_points.values()]
    values = np.concatenate(finite) if finite else np.zeros(0)
    scale = float(np.percentile(values, 99.5)) if values.size else 1.0
    scale = scale if scale > 0 else 1.0
    for m in result.methods:
        files[f"albedo-{m}.exr"] = _write_exr(out / f"albedo-{m}.exr", result.rho[m])
        files[f"albedo-{m}.png"] = _albedo_png(out / f"albedo-{m}.png", result.rho[m], scale)
    files["reasons.png"] = _reason_png(out / "reasons.png", result.reason)
    textures = {}
    if result.uv is not None:
        for m in result.methods:
            texture = uv_texture(result, m, texture_size)
            files[f"texture-{m}.exr"] = _write_exr(out / f"texture-{m}.exr", texture)
            files[f"texture-{m}.png"] = textures[m] = _albedo_png(out / f"texture-{m}.png", texture, scale)
    profiles = reflectance_profiles(result, bins)
    fig = reflectance_profiles_figure(profiles, result.methods)
    fig.savefig(out / "profiles.png", dpi=100)
    files["profiles.png"] = out / "profiles.png"

    h5 = out / "reflectance.h5"
    with h5py.File(h5, "w") as f:
        f.attrs.update(
            format="mirrorgonio-reflectance",
            format_version=1,
            pixel_codes=json.dumps(PIXEL_CODES),
            sample_codes=json.dumps(SAMPLE_CODES),
            methods=json.dumps(list(result.methods)),
        )
        f["reason"] = result.reason
        f["rows"], f["cols"] = result.rows, result.cols
        f["points"], f["normals"], f["faces"] = result.points, result.normals, result.faces
        f["heights"] = result.heights
        f["valid"] = result.valid
        f["sample_code"] = result.sample_code
        f["radiance"] = result.radiance
        if result.uv is not None:
            f["uv"] = result.uv
        for m in result.methods:
            f[f"rho/{m}"] = result.rho_points[m]
            f[f"irradiance/{m}"] = result.irradiance[m]
            f[f"irradiance_rgb/{m}"] = result.irradiance_rgb(m)
    files["reflectance.h5"] = h5

    summary = {
        **(metadata or {}),
        **result.summary(),
        "png_scale": scale,
        "profiles": profiles,
        "pixel_codes": {str(c): PIXEL_SHORT[c] for c in PIXEL_CODES},
        "sample_codes": {str(c): SAMPLE_SHORT[c] for c in SAMPLE_CODES},
    }
    files["report.html"] = out / "report.html"
    files["reflectance.json"] = out / "reflectance.json"
    summary["outputs"] = {name: str(path) for name, path in files.items()}
    from processing.lightmodel import _plain

    (out / "reflectance.json").write_text(json.dumps(_plain(summary), indent=2) + "\n", encoding="utf-8")
    write_reflectance_report(
        out / "report.html",
        summary,
        images={
            **{f"albedo-{m}": out / f"albedo-{m}.png" for m in result.methods},
            "reasons": out / "reasons.png",
            "profiles": out / "profiles.png",
            **{f"texture-{m}": p for m, p in textures.items()},
        },
    )
    result.outputs = files
    return files


# --- from a run file ------------------------------------------------------------------------------------
def _results_for(run_path: Path, out: Path, progress) -> Path:
    """The run's HDR results: beside the run, in ``out``, or made now (in ``out``)."""
    from processing.pipeline import ProcessingError, process_run
    from processing.results import results_path_for

    for folder in (run_path.parent, out):
        candidate = results_path_for(run_path, folder)
        if candidate.is_file():
            return candidate
    log.info("%s: no HDR results yet: merging the brackets into %s", run_path, out)
    try:
        report = process_run(
            run_path, out, steps=("hdr",), progress=(lambda d, t: progress("hdr", d, t)) if progress else None
        )
    except ProcessingError as exc:
        raise ReflectanceError(str(exc)) from None
    return report.results_file


def reflectance_from_run(
    object_run,
    light=None,
    mesh=None,
    out_dir=None,
    *,
    progress=None,
    settings: ReflectanceSettings | None = None,
    texture_size: int = 1024,
    bins: int = 24,
) -> ReflectanceResult:
    """Estimate an object's albedo from its run file and write every output.

    Parameters
    ----------
    object_run : path-like
        The object run (``object-arc`` on a rig with ``[object]``).
    light : path-like, optional
        The light model: a ``.light.json``, or the light run's results folder or file
        (:func:`find_light_model`). Default: the model the run recorded
        (``references.light_model``).
    mesh : path-like, optional
        The object's mesh (default: the rig's ``[object].mesh``). Its ``units_m`` and
        ``pose`` come from the rig's ``[object]`` (metres and the rig frame without one).
    out_dir : path-like, optional
        Folder for the outputs (default ``RUN.reflectance`` beside the run). The run's
        HDR results are looked for beside the run and here, and made here when missing.
    progress : callable, optional
        ``progress(stage, done, total)``, stage ``"hdr"``, ``"rays"`` or ``"lights"``.
    settings : ReflectanceSettings, optional
    texture_size, bins : int
        UV texture size (texels) and the number of height bins of the profiles.

    Raises
    ------
    ReflectanceError
        One line: an unreadable run, mesh or light model, an object run without
        ``[object]`` and no mesh, light results from a different rig, a mesh out of the
        camera's view, no valid point.
    """
    from drivers.contracts.runfile import RunFile, RunFileError, file_sha256
    from processing.hdr import superpixels
    from processing.lightmodel import LightModel, LightModelError
    from processing.pipeline import _light_pose, gain_mismatch, radiometric_gain
    from processing.results import Results, ResultsError
    from processing.trace import RigGeometry

    run_path = Path(object_run)
    out = Path(out_dir) if out_dir is not None else run_path.with_name(f"{run_path.stem}.reflectance")
    warnings: list[str] = []
    try:
        run = RunFile.open(run_path)
    except RunFileError as exc:
        raise ReflectanceError(str(exc)) from None
    with run:
        rig = run.header.rig
        references = run.header.references or {}
        obj = rig.object
        if mesh is None:
            if obj is None:
                raise ReflectanceError(
                    f"{run_path}: the run's rig {rig.name!r} has no [object] and no mesh was given (--mesh)"
                )
            mesh_path = obj.mesh_path()
        else:
            mesh_path = Path(mesh)
        object_pose = obj.pose.to_pose() if obj is not None else None
        mesh_rig = load_mesh(mesh_path, obj.units_m if obj is not None else 1.0, object_pose)
        recorded_mesh = references.get("object_mesh") or {}
        if recorded_mesh.get("sha256") and recorded_mesh["sha256"] != file_sha256(mesh_path):
            warnings.append(
                f"{mesh_path}: not the mesh the run recorded ({recorded_mesh.get('path')}): its contents differ"
            )

        recorded_light = references.get("light_model") or {}
        if light is None:
            if not recorded_light.get("path"):
                raise ReflectanceError(f"{run_path}: the run records no light model: give one with --light")
            light_path = find_light_model(recorded_light["path"])
        else:
            light_path = find_light_model(light)
            if recorded_light.get("sha256") and recorded_light["sha256"] != file_sha256(light_path):
                warnings.append(f"{light_path}: not the light model the run recorded ({recorded_light.get('path')})")
        try:
            light_model = LightModel.load(light_path)
        except LightModelError as exc:
            raise ReflectanceError(str(exc)) from None
        note = check_light_frame(light_model, light_path, rig, run_path)
        if note:
            warnings.append(note)

        out.mkdir(parents=True, exist_ok=True)
        results_file = _results_for(run_path, out, progress)
        geometry = RigGeometry.from_rig(rig)
        try:
            with Results.open(results_file) as results:
                positions = np.flatnonzero(results.hdr_done & run.complete)
                if positions.size < 2:
                    raise ReflectanceError(
                        f"{run_path}: {positions.size} position(s) with frames and an HDR result: "
                        "the albedo needs at least 2 light positions"
                    )
                # DN/s → e⁻/s with the rig's calibrated gain, as the light step: k (e⁻/s per unit
                # radiance) is calibrated with it; the HDR's own estimate only weights the merge.
                gain, gain_source = radiometric_gain(run), "rig"
                mismatch = gain_mismatch(results.noise, gain)
                cfa = results.cfa_pattern
                rates, saturated, poses = [], [], []
                for index in positions:
                    index = int(index)
                    mosaic = results.radiance(index).astype(np.float64) * gain  # DN/s -> e-/s
                    rates.append(superpixels(mosaic, cfa))
                    saturated.append(_superpixel_any(results.saturated(index)))
                    poses.append(_light_pose(run, geometry, index))
        except ResultsError as exc:
            raise ReflectanceError(str(exc)) from None
        run_id = run.header.run_id

    if mismatch is not None:
        if mismatch[0] >= logging.WARNING:
            warnings.append(f"{results_file}: {mismatch[1]}")
        else:
            log.info("%s: %s", results_file, mismatch[1])
    for text in warnings:
        log.warning("%s", text)
    result = estimate_reflectance(
        np.stack(rates),
        np.stack(saturated),
        rig.camera,
        mesh_rig,
        poses,
        light_model,
        object_pose=object_pose,
        up=obj.up if obj is not None else (0.0, 1.0, 0.0),
        housing=(rig.light.housing_radius_m, rig.light.housing_depth_m),
        settings=settings,
        mesh_name=str(mesh_path),
        progress=progress,
    )
    result.warnings[:0] = warnings
    result.metadata = {
        "object_run": str(run_path),
        "run_id": run_id,
        "rig": rig.name,
        "results_file": str(results_file),
        "positions": [int(i) for i in positions],
        "light_model": str(light_path),
        "light_run_id": light_model.provenance.get("run_id", ""),
        "light_units": light_model.units,
        "mesh": str(mesh_path),
        "camera_sensitivity_e_per_s": rig.camera.sensitivity_e_per_s,
        "gain_e_per_dn": gain,
        "gain_source": gain_source,
    }
    write_outputs(result, out, texture_size=texture_size, bins=bins, metadata=result.metadata)
    return result

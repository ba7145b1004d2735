"""The rig description: geometry, calibration and schedule, loaded from TOML.

This module is the contract between the acquisition, the simulated devices and the
processing (see ``docs/rig.md``). Lengths are metres and angles degrees in the TOML
(names end in ``_m`` and ``_deg``); in code, after loading, angles are radians.

An impossible rig is refused with a one-line :class:`RigError` that names the file and
the field.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Final, Literal, Self

import numpy as np
from numpy.typing import ArrayLike
from pydantic import Field, PositiveFloat, PositiveInt, model_validator

from drivers.arm import SoftLimits
from drivers.config_files import ConfigModel, load_model, validate_model
from drivers.contracts.photometric import PhotometricCalibration
from drivers.pose import Pose, angles_from_rotation, rotation_from_angles

# scipy.spatial.transform is imported where a rotation is computed (CameraPose.extrinsics,
# ObjectArc.light_poses): at the top it would more than double the import time of this module,
# which every process imports (the daemon, each worker, every command).

#: Version 2 added the arm's base frame (``[arm] base``) and the tolerances (``[tolerances]``);
#: a version-1 file loads unchanged (the base frame is the rig frame, the tolerances default).
RIG_SCHEMA_VERSION: Final = 2
#: The rigs shipped with the package (package data: also there in a wheel); ``rigs/`` at the top
#: of a checkout links here.
RIGS_DIR = Path(__file__).resolve().parent / "rigs"
DEFAULT_RIG_PATH = RIGS_DIR / "default.toml"

#: Positions in a schedule, and pixels along a sensor's side: bounded so that a typo cannot
#: ask for a schedule or an image that does not fit in memory (the API's ``count`` agrees).
MAX_POSITIONS = 100_000
MAX_SENSOR_SIDE = 100_000
PositionCount = Annotated[int, Field(gt=0, le=MAX_POSITIONS)]
SensorSide = Annotated[int, Field(gt=0, le=MAX_SENSOR_SIDE)]

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
RGB = tuple[float, float, float]


class RigError(ValueError):
    """An impossible or unreadable rig description (one line: file, field, cause)."""


# --- poses at the user's edge ----------------------------------------------------------
class PoseSpec(ConfigModel):
    """A pose: position in metres, fixed-axis X-Y-Z rotation in degrees."""

    position_m: Vec3 = (0.0, 0.0, 0.0)
    rotation_deg: Vec3 = (0.0, 0.0, 0.0)

    def to_pose(self) -> Pose:
        rx, ry, rz = (math.radians(a) for a in self.rotation_deg)
        return Pose(*self.position_m, rx, ry, rz)

    @classmethod
    def of(cls, pose: Pose) -> PoseSpec:
        """The spec of ``pose`` (its angles as :func:`drivers.pose.angles_from_rotation` gives them)."""
        angles = tuple(math.degrees(a) for a in angles_from_rotation(pose.rotation))
        return cls(position_m=tuple(float(x) for x in pose.position), rotation_deg=angles)  # type: ignore[arg-type]


def look_rotation(forward: ArrayLike, x_hint: ArrayLike) -> np.ndarray:
    """Rotation whose z axis is ``forward`` and whose x axis is as close to ``x_hint``."""
    z = np.asarray(forward, dtype=float)
    if np.linalg.norm(z) < 1e-12:
        raise ValueError("the light sits on the point it should aim at")
    z = z / np.linalg.norm(z)
    x = np.asarray(x_hint, dtype=float)
    x = x - z * np.dot(x, z)
    norm = np.linalg.norm(x)
    if norm < 1e-9:
        raise ValueError("the x axis hint is parallel to the viewing direction")
    x /= norm
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


class Orientation(ConfigModel):
    """A fixed light orientation: explicit angles, or the light axis aimed at a point.

    With ``aim_at_m`` the light's +z points from the schedule's middle position at that
    point and its +x lies along ``x_axis`` as far as possible; the orientation is then
    held for every position, as the reference experiment's arm did.
    """

    rotation_deg: Vec3 | None = None
    aim_at_m: Vec3 | None = (0.0, 0.0, 0.0)
    x_axis: Vec3 = (1.0, 0.0, 0.0)

    def rotation_from(self, position: ArrayLike) -> np.ndarray:
        if self.rotation_deg is not None:
            return rotation_from_angles(*(math.radians(a) for a in self.rotation_deg))
        forward = np.asarray(self.aim_at_m) - np.asarray(position, dtype=float)
        return look_rotation(forward, self.x_axis)


# --- the parts of the rig ----------------------------------------------------------------
class CameraPose(ConfigModel):
    """Where the camera is and where it looks.

    Either ``position_m`` + ``look_at_m`` + ``up`` (the image's up direction), or an
    OpenCV extrinsic ``rvec`` (Rodrigues, radians) + ``tvec_m`` with ``x_cam = R X + t``.
    """

    position_m: Vec3 | None = (0.0, 0.0, 0.2)
    look_at_m: Vec3 = (0.0, 0.0, 0.0)
    up: Vec3 = (0.0, 1.0, 0.0)
    rvec: Vec3 | None = None
    tvec_m: Vec3 | None = None

    @model_validator(mode="after")
    def _one_form(self) -> Self:
        if (self.rvec is None) != (self.tvec_m is None):
            raise ValueError("give both rvec and tvec_m, or neither")
        return self

    def extrinsics(self) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV's (R, t): rig point X to camera coordinates ``R @ X + t``."""
        if self.rvec is not None:
            from scipy.spatial.transform import Rotation  # noqa: PLC0415 - heavy (see the imports)

            rot = Rotation.from_rotvec(self.rvec).as_matrix()
            return rot, np.asarray(self.tvec_m, dtype=float)
        centre = np.asarray(self.position_m, dtype=float)
        forward = np.asarray(self.look_at_m, dtype=float) - centre
        z = forward / np.linalg.norm(forward)
        down = -np.asarray(self.up, dtype=float)  # OpenCV's image y points down
        y = down - z * np.dot(down, z)
        if np.linalg.norm(y) < 1e-9:
            raise ValueError("up is parallel to the viewing direction")
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
        rot = np.vstack([x, y, z])
        return rot, -rot @ centre


class ThinLens(ConfigModel):
    """A thin lens focused at ``focus_distance_m`` (along the axis) at ``f_number``."""

    focus_distance_m: PositiveFloat
    f_number: PositiveFloat


class Aperture(ConfigModel):
    """The pinhole's actual shape, as the simulated camera's Fresnel point spread sees it
    (``camera.point_spread = "fresnel"``: the simulated camera's and the processing's templates).

    In the camera's aperture plane, seen from the sensor looking out through the pinhole: x
    along the image's columns, y along its rows. ``circle`` is a hole of ``pinhole_diameter_m``
    (the lens's stop with ``thin_lens``); ``ellipse`` has full ``axes_m`` (its own x then y
    diameter), its x axis ``angle_deg`` from the camera's +x towards +y; ``mask`` is a greyscale
    PNG of the hole's transmission (grey level over the format's full scale), ``mask_pixel_m``
    metres a pixel, its rows along y and its transmission-weighted centroid the hole's centre.
    A circle or an ellipse may have a rough edge: a seeded random radial perturbation of RMS
    ``edge_roughness_rms_m`` whose Gaussian correlation length along the edge is
    ``edge_correlation_m``.
    """

    shape: Literal["circle", "ellipse", "mask"] = "circle"
    axes_m: tuple[PositiveFloat, PositiveFloat] | None = None
    angle_deg: float = 0.0
    mask: str | None = Field(default=None, min_length=1)
    mask_pixel_m: PositiveFloat | None = None
    edge_roughness_rms_m: Annotated[float, Field(ge=0.0)] = 0.0
    edge_correlation_m: PositiveFloat = 5e-6
    roughness_seed: Annotated[int, Field(ge=0)] = 0

    @model_validator(mode="after")
    def _one_shape(self) -> Self:
        if (self.shape == "ellipse") != (self.axes_m is not None):
            raise ValueError("axes_m: required for an ellipse, and only for one")
        if self.shape != "ellipse" and self.angle_deg != 0.0:
            raise ValueError("angle_deg: only for an ellipse")
        for name in ("mask", "mask_pixel_m"):
            if (self.shape == "mask") != (getattr(self, name) is not None):
                raise ValueError(f"{name}: required for a mask, and only for one")
        if self.shape == "mask" and self.edge_roughness_rms_m > 0:
            raise ValueError("edge_roughness_rms_m: a mask already has its own edge")
        return self

    def mask_path(self, base: Path | None = None) -> Path | None:
        if self.mask is None:
            return None
        path = Path(self.mask).expanduser()
        return path if path.is_absolute() or base is None else base / path


class MeasuredPointSpread(ConfigModel):
    """A point spread the lab measured, which the processing's templates take instead of
    computing one from ``point_spread`` (the simulated camera keeps its own physics).

    ``file`` is a NumPy ``.npz`` holding ``psf`` (3, h, w): the image of a small LED through
    the pinhole, one linear image per channel on the sensor's own pixels (dark frame
    subtracted); ``distance_m``: the LED's distance in front of the pinhole; ``pixel_pitch_m``:
    the sensor's pitch. A relative path is taken against the rig file's folder.
    """

    file: str = Field(min_length=1)

    def path(self, base: Path | None = None) -> Path:
        path = Path(self.file).expanduser()
        return path if path.is_absolute() or base is None else base / path


class SpectralResponse(ConfigModel):
    """Tabulated sensitivity curves of the three channels: the relative response of R, G and B
    at each of ``wavelengths_m`` (ascending), linear in between and zero outside."""

    wavelengths_m: list[PositiveFloat] = Field(min_length=2, max_length=10_000)
    r: list[Annotated[float, Field(ge=0.0)]]
    g: list[Annotated[float, Field(ge=0.0)]]
    b: list[Annotated[float, Field(ge=0.0)]]

    @model_validator(mode="after")
    def _a_curve_each(self) -> Self:
        if any(b <= a for a, b in zip(self.wavelengths_m, self.wavelengths_m[1:], strict=False)):
            raise ValueError("wavelengths_m: must be strictly ascending")
        for name in ("r", "g", "b"):
            values = getattr(self, name)
            if len(values) != len(self.wavelengths_m):
                raise ValueError(f"{name}: {len(values)} values for {len(self.wavelengths_m)} wavelengths")
            if not any(v > 0 for v in values):
                raise ValueError(f"{name}: the channel responds nowhere")
        return self

    def curve(self, channel: int) -> tuple[np.ndarray, np.ndarray]:
        """(wavelengths in metres, relative response) of channel 0, 1 or 2 (R, G, B)."""
        values = (self.r, self.g, self.b)[channel]
        return np.asarray(self.wavelengths_m, dtype=float), np.asarray(values, dtype=float)


class Camera(ConfigModel):
    """The camera: a pinhole of finite diameter, or a thin lens.

    ``sensor_distance_m`` is the pinhole-to-sensor (or lens-to-sensor) distance. The
    radiometric ``sensitivity_e_per_s`` is for simulation: the electrons per second a
    pixel on the axis collects from a scene of unit radiance through the whole aperture.
    """

    pinhole_diameter_m: PositiveFloat = 0.2e-3
    sensor_distance_m: PositiveFloat = 0.025
    thin_lens: ThinLens | None = None
    pixel_pitch_m: PositiveFloat = 5.9e-6
    width: SensorSide = 2000
    height: SensorSide = 1312
    principal_point_px: Vec2 | None = None
    pose: CameraPose = CameraPose()
    cfa_pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"] = "RGGB"
    bit_depth: Annotated[int, Field(ge=8, le=16)] = 12
    black_level_dn: Annotated[int, Field(ge=0)] = 64
    white_level_dn: PositiveInt | None = None
    full_well_e: PositiveFloat = 20000.0
    read_noise_e: Annotated[float, Field(ge=0.0)] = 3.0
    channel_wavelengths_m: RGB = (610e-9, 540e-9, 465e-9)
    channel_bandwidths_m: tuple[
        Annotated[float, Field(ge=0.0)], Annotated[float, Field(ge=0.0)], Annotated[float, Field(ge=0.0)]
    ] = (80e-9, 80e-9, 80e-9)
    spectral_response: SpectralResponse | None = None
    aperture: Aperture = Aperture()
    point_spread: Literal["geometric-airy", "fresnel"] = "fresnel"
    measured_point_spread: MeasuredPointSpread | None = None
    sensitivity_e_per_s: PositiveFloat = 1000.0
    photometric: PhotometricCalibration | None = None

    @model_validator(mode="after")
    def _levels(self) -> Self:
        top = (1 << self.bit_depth) - 1
        if self.white_level_dn is not None and self.white_level_dn > top:
            raise ValueError(f"white_level_dn {self.white_level_dn} exceeds the {self.bit_depth}-bit range")
        if self.black_level_dn >= self.white_level:
            raise ValueError("black_level_dn must be below the white level")
        if self.principal_point_px is not None:
            cx, cy = self.principal_point_px
            if not (0 <= cx < self.width and 0 <= cy < self.height):
                raise ValueError("principal_point_px lies outside the sensor")
        for centre, width in zip(self.channel_wavelengths_m, self.channel_bandwidths_m, strict=True):
            if width >= centre:
                raise ValueError("channel_bandwidths_m: each band must be narrower than its channel's wavelength")
        rough = self.aperture.edge_roughness_rms_m
        if rough > 0 and rough >= 0.1 * min(self.aperture.axes_m or (self.aperture_diameter_m,)) / 2:
            raise ValueError("aperture.edge_roughness_rms_m: must be below 10 % of the aperture's radius")
        return self

    @property
    def white_level(self) -> int:
        return self.white_level_dn if self.white_level_dn is not None else (1 << self.bit_depth) - 1

    @property
    def principal_point(self) -> tuple[float, float]:
        if self.principal_point_px is not None:
            return self.principal_point_px
        return ((self.width - 1) / 2.0, (self.height - 1) / 2.0)

    @property
    def aperture_diameter_m(self) -> float:
        if self.thin_lens is not None:
            focal = 1.0 / (1.0 / self.sensor_distance_m + 1.0 / self.thin_lens.focus_distance_m)
            return focal / self.thin_lens.f_number
        return self.pinhole_diameter_m

    @property
    def f_number(self) -> float:
        """The working f-number that sets diffraction: sensor distance over aperture."""
        return self.sensor_distance_m / self.aperture_diameter_m

    @property
    def gain_e_per_dn(self) -> float:
        """Conversion gain that maps the full well onto the white level."""
        return self.full_well_e / (self.white_level - self.black_level_dn)

    def camera_matrix(self) -> np.ndarray:
        """OpenCV's intrinsic matrix K (focal length in pixels)."""
        fpx = self.sensor_distance_m / self.pixel_pitch_m
        cx, cy = self.principal_point
        return np.array([[fpx, 0.0, cx], [0.0, fpx, cy], [0.0, 0.0, 1.0]])

    def centre(self) -> np.ndarray:
        rot, t = self.pose.extrinsics()
        return -rot.T @ t


class Ball(ConfigModel):
    """The mirrored ball: a conductor with complex refractive index n + ik per channel.

    The defaults are chrome in the red, green and blue channels (normal-incidence
    reflectance about 0.55).
    """

    centre_m: Vec3 = (0.0, 0.0, 0.0)
    radius_m: PositiveFloat = 0.0254
    n: RGB = (3.20, 3.10, 2.60)
    k: RGB = (3.30, 3.30, 3.20)


class Light(ConfigModel):
    """The light's mount and housing.

    ``light_to_tool`` is the light frame expressed in the arm's tool frame. The housing
    is an opaque cylinder of ``housing_radius_m`` behind the light plane (z from
    ``-housing_depth_m`` to 0 in the light frame); it blocks any ray that meets it.
    """

    light_to_tool: PoseSpec = PoseSpec()
    housing_radius_m: Annotated[float, Field(ge=0.0)] = 0.012
    housing_depth_m: Annotated[float, Field(ge=0.0)] = 0.05


def _radians(range_deg: Vec2) -> tuple[float, float]:
    """A (low, high) range in degrees, in radians."""
    low, high = range_deg
    return math.radians(low), math.radians(high)


class AxisRange(ConfigModel):
    x_m: Vec2 = (-0.25, 0.25)
    y_m: Vec2 = (-0.25, 0.25)
    z_m: Vec2 = (0.0, 0.45)
    rx_deg: Vec2 = (-180.0, 180.0)
    ry_deg: Vec2 = (-180.0, 180.0)
    rz_deg: Vec2 = (-180.0, 180.0)

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        for name in type(self).model_fields:
            low, high = getattr(self, name)
            if low > high:
                raise ValueError(f"{name}: lower limit {low} above upper limit {high}")
        return self

    def to_soft_limits(self) -> SoftLimits:
        return SoftLimits(
            {
                "x": self.x_m,
                "y": self.y_m,
                "z": self.z_m,
                "rx": _radians(self.rx_deg),
                "ry": _radians(self.ry_deg),
                "rz": _radians(self.rz_deg),
            }
        )


class Arm(ConfigModel):
    """The arm: its soft limits (on the tool pose, in the arm's own frame) and where that frame
    is. ``base`` is the arm's base frame in the rig frame: the tool poses the arm is commanded
    to and reads back are in the base frame, and the light sits at
    ``base ∘ tool ∘ light.light_to_tool`` in the rig frame. Identity by default (the arm's frame
    is the rig frame)."""

    soft_limits: AxisRange = AxisRange()
    base: PoseSpec = PoseSpec()


class Tolerances(ConfigModel):
    """How far each measured number of the rig may be off: the bounds the processing fits the
    rig's numbers within (``docs/rig.md``, ``docs/lab-guide.md``). The defaults are what a careful
    lab measures with a ruler, a protractor and a datasheet; a lab that measured better says so.
    """

    camera_rotation_deg: PositiveFloat = 1.0
    camera_position_m: PositiveFloat = 0.005
    principal_point_px: PositiveFloat = 20.0
    sensor_distance_fraction: Annotated[float, Field(gt=0.0, lt=0.5)] = 0.03
    pinhole_fraction: Annotated[float, Field(gt=0.0, lt=0.5)] = 0.25
    arm_base_rotation_deg: PositiveFloat = 1.0
    arm_base_position_m: PositiveFloat = 0.003
    light_rotation_deg: PositiveFloat = 2.0
    light_position_m: PositiveFloat = 0.002
    ball_radius_m: PositiveFloat = 5e-5
    pinhole_ellipticity: Annotated[float, Field(gt=0.0, lt=0.5)] = 0.1


# --- schedules ---------------------------------------------------------------------------
class LightSweep(ConfigModel):
    """Positions ``start + i * step`` for i in 0..count-1, at one fixed orientation."""

    kind: Literal["light-sweep"] = "light-sweep"
    start_m: Vec3 = (-0.08125, 0.04, 0.10)
    step_m: Vec3 = (0.0025, 0.0, 0.0)
    count: PositionCount = 66
    orientation: Orientation = Orientation()

    def light_poses(self) -> list[Pose]:
        start, step = np.asarray(self.start_m), np.asarray(self.step_m)
        positions = [start + i * step for i in range(self.count)]
        rotation = self.orientation.rotation_from(start + 0.5 * (self.count - 1) * step)
        return [Pose.from_rotation(p, rotation) for p in positions]


class Raster(ConfigModel):
    """A 2-D grid ``origin + i * step_u + j * step_v``, row by row, fixed orientation."""

    kind: Literal["raster"] = "raster"
    origin_m: Vec3 = (-0.01, 0.03, 0.10)
    step_u_m: Vec3 = (0.0025, 0.0, 0.0)
    step_v_m: Vec3 = (0.0, 0.0025, 0.0)
    count_u: PositionCount = 9
    count_v: PositionCount = 9
    orientation: Orientation = Orientation()

    @model_validator(mode="after")
    def _not_too_many(self) -> Self:
        if self.count_u * self.count_v > MAX_POSITIONS:
            raise ValueError(f"count_u × count_v = {self.count_u * self.count_v}: more than {MAX_POSITIONS} positions")
        return self

    def light_poses(self) -> list[Pose]:
        origin = np.asarray(self.origin_m)
        su, sv = np.asarray(self.step_u_m), np.asarray(self.step_v_m)
        middle = origin + 0.5 * (self.count_u - 1) * su + 0.5 * (self.count_v - 1) * sv
        rotation = self.orientation.rotation_from(middle)
        return [
            Pose.from_rotation(origin + i * su + j * sv, rotation)
            for j in range(self.count_v)
            for i in range(self.count_u)
        ]


class ObjectArc(ConfigModel):
    """Light positions on an arc around an object, each aimed at the object.

    Position k is ``centre + radius * Rot(axis, angle_k) @ reference_direction``: with
    the defaults the light starts towards the camera (+z) and rises towards +y by
    10 to 50 degrees, at 30 cm, as in the reference experiment.
    """

    kind: Literal["object-arc"] = "object-arc"
    centre_m: Vec3 = (0.0, 0.0, 0.0)
    radius_m: PositiveFloat = 0.30
    angles_deg: list[float] = Field(
        default_factory=lambda: [10.0, 20.0, 30.0, 40.0, 50.0], min_length=1, max_length=MAX_POSITIONS
    )
    reference_direction: Vec3 = (0.0, 0.0, 1.0)
    axis: Vec3 = (-1.0, 0.0, 0.0)
    x_axis: Vec3 = (1.0, 0.0, 0.0)

    def light_poses(self) -> list[Pose]:
        from scipy.spatial.transform import Rotation  # noqa: PLC0415 - heavy (see the imports)

        axis = np.asarray(self.axis, dtype=float)
        axis /= np.linalg.norm(axis)
        ref = np.asarray(self.reference_direction, dtype=float)
        ref /= np.linalg.norm(ref)
        centre = np.asarray(self.centre_m)
        poses = []
        for angle in self.angles_deg:
            direction = Rotation.from_rotvec(axis * math.radians(angle)).apply(ref)
            position = centre + self.radius_m * direction
            poses.append(Pose.from_rotation(position, look_rotation(-direction, self.x_axis)))
        return poses


class ObjectDome(ConfigModel):
    """Light positions over the hemisphere on the camera's side of an object, aimed at it.

    Ring k holds ``counts[k]`` lights evenly spread in azimuth about ``reference_direction``
    (from the object towards the camera), ``polar_deg[k]`` away from it, at ``radius_m``
    (one distance, or one per ring). Successive rings are turned by half a step so their
    azimuths interleave, and walked in alternating directions so the arm's moves stay
    short. The defaults (48 positions, 12° to 72° from the camera's direction, 25 cm)
    light every front-facing normal up to about 36° from the view direction in its mirror
    direction, which is what a glossy surface needs: a highlight sample per texel.
    """

    kind: Literal["object-dome"] = "object-dome"
    centre_m: Vec3 = (0.0, 0.0, 0.0)
    radius_m: PositiveFloat | list[PositiveFloat] = 0.25
    polar_deg: list[Annotated[float, Field(ge=0.0, lt=90.0)]] = Field(
        default_factory=lambda: [12.0, 27.0, 42.0, 57.0, 72.0], min_length=1, max_length=1000
    )
    counts: list[Annotated[int, Field(ge=1, le=1000)]] = Field(
        default_factory=lambda: [4, 8, 10, 12, 14], min_length=1, max_length=1000
    )
    reference_direction: Vec3 = (0.0, 0.0, 1.0)
    x_axis: Vec3 = (1.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _rings_agree(self) -> Self:
        if len(self.counts) != len(self.polar_deg):
            raise ValueError(f"counts: {len(self.counts)} rings, but polar_deg has {len(self.polar_deg)}")
        if isinstance(self.radius_m, list) and len(self.radius_m) != len(self.polar_deg):
            raise ValueError(f"radius_m: {len(self.radius_m)} distances for {len(self.polar_deg)} rings")
        if sum(self.counts) > MAX_POSITIONS:
            raise ValueError(f"counts: {sum(self.counts)} positions, more than {MAX_POSITIONS}")
        if not np.linalg.norm(self.reference_direction) > 0:
            raise ValueError("reference_direction: must be a non-zero vector")
        return self

    def light_poses(self) -> list[Pose]:
        pole = np.asarray(self.reference_direction, dtype=float)
        pole /= np.linalg.norm(pole)
        # An orthonormal frame about the pole: e1 along the x-axis hint where it is not parallel.
        hint = np.asarray(self.x_axis, dtype=float)
        e1 = hint - (hint @ pole) * pole
        if np.linalg.norm(e1) < 1e-9:
            e1 = np.cross(pole, [0.0, 1.0, 0.0] if abs(pole[1]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(pole, e1)
        radii = self.radius_m if isinstance(self.radius_m, list) else [self.radius_m] * len(self.counts)
        centre = np.asarray(self.centre_m)
        poses = []
        for ring, (polar, count, radius) in enumerate(zip(self.polar_deg, self.counts, radii, strict=True)):
            step = 2.0 * math.pi / count
            azimuths = (np.arange(count) + 0.5 * (ring % 2)) * step
            if ring % 2:
                azimuths = azimuths[::-1]
            t = math.radians(polar)
            for phi in azimuths:
                direction = math.cos(t) * pole + math.sin(t) * (math.cos(phi) * e1 + math.sin(phi) * e2)
                poses.append(Pose.from_rotation(centre + radius * direction, look_rotation(-direction, self.x_axis)))
        return poses


class PoseList(ConfigModel):
    """An explicit list of light poses."""

    kind: Literal["poses"] = "poses"
    poses: list[PoseSpec] = Field(min_length=1, max_length=MAX_POSITIONS)

    def light_poses(self) -> list[Pose]:
        return [p.to_pose() for p in self.poses]


Schedule = Annotated[LightSweep | Raster | ObjectArc | ObjectDome | PoseList, Field(discriminator="kind")]


class SceneObject(ConfigModel):
    """An object photographed in place of the ball (reflectance runs).

    ``mesh`` is a PLY, OBJ or STL file (read with trimesh; from a 3D digitiser in real
    use); a relative path is relative to the rig file's folder. ``units_m`` converts the
    mesh's units to metres (0.001 for millimetres). ``pose`` places the object frame in
    the rig frame (``x_rig = R·x_object + t``). ``up`` is the object's vertical axis in its
    own frame, along which reflectance profiles are drawn.
    """

    mesh: str = Field(min_length=1)
    units_m: PositiveFloat = 1.0
    pose: PoseSpec = PoseSpec()
    up: Vec3 = (0.0, 1.0, 0.0)

    @model_validator(mode="after")
    def _up_is_a_direction(self) -> Self:
        if not np.linalg.norm(self.up) > 0:
            raise ValueError("up: must be a non-zero vector")
        return self

    def mesh_path(self, base: Path | None = None) -> Path:
        path = Path(self.mesh).expanduser()
        return path if path.is_absolute() or base is None else base / path


class Simulation(ConfigModel):
    """Settings used only by the simulated devices.

    ``surface`` names the simulated object's reflectance (``sim_devices/surfaces/``: a base
    albedo, painted patches and an optional specular lobe) when the rig has an ``object``.
    Without ``diffraction`` the simulated camera's blur is the aperture's geometric shadow
    alone (``camera.point_spread`` otherwise).
    """

    truth: str = "five-gaussians"
    seed: int = 0
    diffraction: bool = True
    noise: bool = True
    surface: str = "uniform"


# --- the rig -------------------------------------------------------------------------------
class Rig(ConfigModel):
    """A whole rig: camera, ball, light, arm and the schedule of light poses."""

    schema_version: Literal[1, 2] = RIG_SCHEMA_VERSION
    name: str = "default"
    camera: Camera = Camera()
    ball: Ball = Ball()
    light: Light = Light()
    arm: Arm = Arm()
    schedule: Schedule = LightSweep()
    tolerances: Tolerances = Tolerances()
    simulation: Simulation = Simulation()
    object: SceneObject | None = None

    # Derived views ------------------------------------------------------------------
    def light_poses(self) -> list[Pose]:
        """Where the light is at each schedule position (rig frame)."""
        return self.schedule.light_poses()

    def tool_poses(self) -> list[Pose]:
        """What the arm is commanded to, in its base frame: ``base⁻¹ ∘ light ∘ light_to_tool⁻¹``."""
        light_from_tool = self.light.light_to_tool.to_pose().inverse()
        tools = [p.compose(light_from_tool) for p in self.light_poses()]
        if self.arm.base == PoseSpec():  # the arm's frame is the rig frame
            return tools
        rig_to_base = self.arm.base.to_pose().inverse()
        return [rig_to_base.compose(tool) for tool in tools]

    def light_pose(self, tool_pose: Pose) -> Pose:
        """Where the light is (rig frame) with the tool at ``tool_pose`` (the arm's base frame)."""
        light = tool_pose.compose(self.light.light_to_tool.to_pose())
        return light if self.arm.base == PoseSpec() else self.arm.base.to_pose().compose(light)

    def soft_limits(self) -> SoftLimits:
        return self.arm.soft_limits.to_soft_limits()

    def ball_outline_px(self, points: int = 180) -> np.ndarray:
        """The ball's expected outline on the sensor: ``points`` (col, row) pixel positions.

        The rays from the camera's centre that graze the ball touch it on a circle; that circle
        through the pinhole (OpenCV's K, R, t, no distortion) is the outline, an ellipse off the
        axis. What the technician aligns the rig with: the ball's image should fill it.
        """
        rot, t = self.camera.pose.extrinsics()
        eye = -rot.T @ t
        centre = np.asarray(self.ball.centre_m, dtype=float)
        axis = centre - eye
        distance = float(np.linalg.norm(axis))
        axis /= distance
        radius = self.ball.radius_m
        # The tangent circle: centre at eye + axis * (d - r²/d), radius r·√(d² - r²)/d.
        ring_centre = eye + axis * (distance - radius * radius / distance)
        ring_radius = radius * math.sqrt(distance * distance - radius * radius) / distance
        helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(axis, helper)
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        angles = np.linspace(0.0, 2.0 * math.pi, points, endpoint=False)
        ring = ring_centre + ring_radius * (np.outer(np.cos(angles), u) + np.outer(np.sin(angles), v))
        uvw = (ring @ rot.T + t) @ self.camera.camera_matrix().T
        return np.asarray(uvw[:, :2] / uvw[:, 2:3], dtype=float)

    @model_validator(mode="before")
    @classmethod
    def _object_scene_blur(cls, data: Any) -> Any:
        """An object scene is rendered with the geometric⊗Airy blur: where the rig does not
        name a point spread, that one (a rig that names ``fresnel`` with an object is refused)."""
        if isinstance(data, dict) and data.get("object") is not None:
            camera = data.get("camera")
            camera = dict(camera) if isinstance(camera, dict) else {} if camera is None else camera
            if isinstance(camera, dict) and "point_spread" not in camera:
                data = {**data, "camera": {**camera, "point_spread": "geometric-airy"}}
        return data

    # Physical checks --------------------------------------------------------------------
    @model_validator(mode="after")
    def _physically_possible(self) -> Self:
        centre = np.asarray(self.ball.centre_m)
        radius = self.ball.radius_m
        try:
            camera_centre = self.camera.centre()
        except ValueError as exc:  # degenerate look-at
            raise ValueError(f"camera.pose: {exc}") from None
        if np.linalg.norm(camera_centre - centre) <= radius:
            raise ValueError("camera.pose: the camera is inside the ball")
        rot, t = self.camera.pose.extrinsics()
        if (rot @ centre + t)[2] <= radius:
            raise ValueError("camera.pose: the ball is not in front of the camera")
        if self.object is not None and self.camera.point_spread == "fresnel":
            raise ValueError("camera.point_spread: the object scene has no Fresnel point spread (geometric-airy)")

        try:
            lights = self.light_poses()
        except ValueError as exc:
            raise ValueError(f"schedule: {exc}") from None
        clearance = radius + self.light.housing_radius_m
        for i, pose in enumerate(lights):
            if np.linalg.norm(pose.position - centre) <= radius:
                raise ValueError(f"schedule: position {i}: the light is inside the ball")
        for i in range(len(lights) - 1):
            a, b = lights[i].position, lights[i + 1].position
            if _segment_distance(centre, a, b) <= clearance:
                raise ValueError(f"schedule: the light's path from position {i} to {i + 1} crosses the ball")
        limits = self.soft_limits()
        for i, tool in enumerate(self.tool_poses()):
            problem = limits.violation(tool)
            if problem is not None:
                raise ValueError(f"schedule: position {i}: tool pose {problem} (arm.soft_limits)")
        return self


def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    denom = float(np.dot(ab, ab))
    s = 0.0 if denom == 0.0 else float(np.clip(np.dot(point - a, ab) / denom, 0.0, 1.0))
    return float(np.linalg.norm(point - (a + s * ab)))


# --- loading -------------------------------------------------------------------------------
def rig_from_dict(data: dict[str, Any], source: str = "<rig>") -> Rig:
    """Validate a rig description given as a dictionary (the parsed TOML)."""
    return validate_model(Rig, data, source, RigError)


def load_rig(path: str | Path | None = None) -> Rig:
    """Load and validate a rig TOML file (the default rig when ``path`` is None).

    An object's relative mesh path, an aperture mask's and a measured point spread's are made
    absolute against the rig file's folder, so the rig stored in a run file still finds them.
    """
    path = Path(path) if path is not None else DEFAULT_RIG_PATH
    rig = load_model(path, Rig, "rig file", RigError)
    if rig.object is not None:
        mesh = rig.object.mesh_path(path.resolve().parent)
        rig = rig.model_copy(update={"object": rig.object.model_copy(update={"mesh": str(mesh)})})
    mask = rig.camera.aperture.mask_path(path.resolve().parent)
    if mask is not None:
        aperture = rig.camera.aperture.model_copy(update={"mask": str(mask)})
        rig = rig.model_copy(update={"camera": rig.camera.model_copy(update={"aperture": aperture})})
    measured = rig.camera.measured_point_spread
    if measured is not None:
        measured = measured.model_copy(update={"file": str(measured.path(path.resolve().parent))})
        rig = rig.model_copy(update={"camera": rig.camera.model_copy(update={"measured_point_spread": measured})})
    return rig


def rig_to_toml_dict(rig: Rig) -> dict[str, Any]:
    """The rig as plain data (for storing inside run files), None values dropped."""
    return rig.model_dump(mode="json", exclude_none=True)


def write_rig(rig: Rig, path: str | Path, comment: str = "") -> Path:
    """``rig`` as a rig file at ``path`` (TOML; :func:`load_rig` reads it back the same), with
    ``comment`` as its opening lines."""
    import tomli_w  # noqa: PLC0415 - only the processing writes rig files; the daemon's start stays light

    head = "".join(f"# {line}\n" if line else "#\n" for line in comment.splitlines())
    path = Path(path)
    path.write_text(head + tomli_w.dumps(rig_to_toml_dict(rig)), encoding="utf-8")
    return path

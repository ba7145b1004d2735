"""Chief rays: camera → mirrored ball → light plane, for every pixel on the ball.

Written for the processing and independently of the simulated camera (``sim_devices``):
pixels are back-projected with OpenCV's intrinsic matrix, and the geometry is done with
(N, 3) vectors in the rig frame. For each pixel the chief ray (through the pinhole's
centre) gives where on the light plane its light came from (u, v), the direction it left
in (θ, φ, in the light frame), the ball's Fresnel reflectance at the angle of incidence,
the ``cos⁴β`` fall-off of the sensor, and the pixel's footprint area on the light plane.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import cast

import numba
import numpy as np
from numpy.typing import ArrayLike

from drivers.contracts.rig import Camera, PoseSpec, Rig
from drivers.contracts.runfile import RunFile
from drivers.pose import Pose


@dataclass(frozen=True)
class RigGeometry:
    """The rig's numbers in the form the tracer uses (rig frame, metres)."""

    K: np.ndarray
    K_inv: np.ndarray
    R: np.ndarray  # rig -> camera
    t: np.ndarray
    camera_centre: np.ndarray
    sensor_distance: float
    pitch: float
    aperture_radius: float
    ball_centre: np.ndarray
    ball_radius: float
    n: np.ndarray
    k: np.ndarray
    light_to_tool: Pose
    housing_radius: float
    housing_depth: float
    wavelengths: np.ndarray
    width: int
    height: int
    inverse_focal: float = 0.0  # 1/F of a thin lens; 0 for a pinhole
    arm_base: Pose | None = None  # the arm's base frame in the rig frame; None: the rig frame
    # The aperture's shape as a symmetric matrix (xx, xy, yy) over the circle of aperture_radius,
    # camera frame: (1, 0, 1) a circle; an ellipse's axes are its eigenvalues (the Fresnel pupil).
    aperture_shape: tuple[float, float, float] = (1.0, 0.0, 1.0)

    def with_sensor_distance(self, sensor_distance: float) -> RigGeometry:
        """The same rig with the sensor ``sensor_distance`` behind the pinhole (or lens): the
        focal length in pixels scales with it; a thin lens keeps its focus distance."""

        K = self.K.copy()
        K[0, 0] = K[1, 1] = sensor_distance / self.pitch
        inverse_focal = self.inverse_focal
        if inverse_focal:  # 1/F = 1/f + 1/focus: the focus distance held
            inverse_focal += 1.0 / sensor_distance - 1.0 / self.sensor_distance
        return replace(
            self, K=K, K_inv=np.linalg.inv(K), sensor_distance=float(sensor_distance), inverse_focal=inverse_focal
        )

    @classmethod
    def from_rig(cls, rig: Rig, ball_centre: Sequence[float] | np.ndarray | None = None) -> RigGeometry:
        cam = rig.camera
        R, t = cam.pose.extrinsics()
        K = cam.camera_matrix()
        return cls(
            K=K,
            K_inv=np.linalg.inv(K),
            R=R,
            t=np.asarray(t, float),
            camera_centre=-R.T @ t,
            sensor_distance=cam.sensor_distance_m,
            pitch=cam.pixel_pitch_m,
            aperture_radius=cam.aperture_diameter_m / 2.0,
            ball_centre=np.asarray(ball_centre if ball_centre is not None else rig.ball.centre_m, float),
            ball_radius=rig.ball.radius_m,
            n=np.asarray(rig.ball.n, float),
            k=np.asarray(rig.ball.k, float),
            light_to_tool=rig.light.light_to_tool.to_pose(),
            housing_radius=rig.light.housing_radius_m,
            housing_depth=rig.light.housing_depth_m,
            wavelengths=np.asarray(cam.channel_wavelengths_m, float),
            width=cam.width,
            height=cam.height,
            inverse_focal=(1.0 / cam.sensor_distance_m + 1.0 / cam.thin_lens.focus_distance_m)
            if cam.thin_lens
            else 0.0,
            arm_base=None if rig.arm.base == PoseSpec() else rig.arm.base.to_pose(),
            aperture_shape=_aperture_shape(cam),
        )

    def pixel_directions(self, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Unit directions (N, 3) in the rig frame of the chief rays of pixels (col, row)."""
        homogeneous = np.stack([cols, rows, np.ones_like(cols)], axis=-1).astype(float)
        in_camera = homogeneous @ self.K_inv.T
        in_rig = in_camera @ self.R  # R.T @ d for each row
        return in_rig / np.linalg.norm(in_rig, axis=-1, keepdims=True)

    def cos4(self, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """``cos⁴β`` of the flat sensor behind the pinhole, β the chief ray's off-axis angle."""
        x = (cols - self.K[0, 2]) / self.K[0, 0]
        y = (rows - self.K[1, 2]) / self.K[1, 1]
        return 1.0 / (1.0 + x * x + y * y) ** 2

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of rig-frame points through the pinhole's centre."""
        cam = points @ self.R.T + self.t
        uvw = cam @ self.K.T
        return uvw[..., :2] / uvw[..., 2:3]


def conductor_reflectance(cos_incidence: np.ndarray, n: ArrayLike, k: ArrayLike) -> np.ndarray:
    """Unpolarised Fresnel reflectance (N, C) of a metal of index n + ik (complex form).

    Examples
    --------
    At normal incidence ``((n - 1)² + k²) / ((n + 1)² + k²)``, and 1 at grazing incidence:

    >>> conductor_reflectance([1.0, 0.0], n=[3.0], k=[3.0]).round(3).tolist()
    [[0.52], [1.0]]
    """
    m = (np.asarray(n) + 1j * np.asarray(k))[None, :]
    c = np.clip(np.asarray(cos_incidence), 0.0, 1.0)[:, None]
    root = np.sqrt(m * m - (1.0 - c * c))  # m * cos(theta_t)
    r_s = (c - root) / (c + root)
    r_p = (m * m * c - root) / (m * m * c + root)
    return 0.5 * (np.abs(r_s) ** 2 + np.abs(r_p) ** 2)


@dataclass
class ChiefRays:
    """Chief-ray trace of a set of pixels at one light pose (all arrays per pixel)."""

    cols: np.ndarray
    rows: np.ndarray
    hits_ball: np.ndarray
    reaches_plane: np.ndarray
    blocked: np.ndarray  # the light housing is in the way of the camera's view
    valid: np.ndarray
    u: np.ndarray
    v: np.ndarray
    theta: np.ndarray
    phi: np.ndarray
    alpha: np.ndarray  # angle of incidence on the ball
    fresnel: np.ndarray  # (N, 3)
    cos4: np.ndarray
    ball_points: np.ndarray  # (N, 3)
    deflection: np.ndarray  # angle between the camera's ray and the reflected ray


def housing_blocks(start: np.ndarray, end: np.ndarray, light: Pose, radius: float, depth: float) -> np.ndarray:
    """Segments (rig frame) that pass through the housing cylinder behind the light plane.

    In the light frame the segment is ``a + s d`` for s in [0, 1]; it meets the solid
    cylinder where three intervals of s overlap: [0, 1], the slab -depth <= z <= 0, and
    the roots of (a_x + s d_x)² + (a_y + s d_y)² <= r².
    """
    if radius <= 0:
        return np.zeros(len(start), dtype=bool)
    rot, origin = light.rotation, light.position
    a = (start - origin) @ rot
    d = (end - start) @ rot
    lo, hi = np.zeros(len(a)), np.ones(len(a))
    with np.errstate(divide="ignore", invalid="ignore"):
        z0, z1 = (-depth - a[:, 2]) / d[:, 2], (0.0 - a[:, 2]) / d[:, 2]
    flat = np.abs(d[:, 2]) < 1e-15
    inside_slab = (a[:, 2] >= -depth) & (a[:, 2] <= 0.0)
    lo = np.where(flat, np.where(inside_slab, lo, np.inf), np.maximum(lo, np.minimum(z0, z1)))
    hi = np.where(flat, hi, np.minimum(hi, np.maximum(z0, z1)))
    qa = d[:, 0] ** 2 + d[:, 1] ** 2
    qb = 2.0 * (a[:, 0] * d[:, 0] + a[:, 1] * d[:, 1])
    qc = a[:, 0] ** 2 + a[:, 1] ** 2 - radius**2
    disc = qb * qb - 4.0 * qa * qc
    parallel = qa < 1e-30
    root = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r0 = np.where(parallel, np.where(qc <= 0, -np.inf, np.inf), (-qb - root) / (2.0 * qa))
        r1 = np.where(parallel, np.where(qc <= 0, np.inf, -np.inf), (-qb + root) / (2.0 * qa))
    meets_cylinder = parallel | (disc >= 0.0)
    return meets_cylinder & (np.maximum(lo, r0) <= np.minimum(hi, r1))


def trace_pixels(geometry: RigGeometry, light_pose: Pose, cols: ArrayLike, rows: ArrayLike) -> ChiefRays:
    """Trace the chief rays of the given pixels with the light at ``light_pose``."""
    cols = np.asarray(cols, float).ravel()
    rows = np.asarray(rows, float).ravel()
    d = geometry.pixel_directions(cols, rows)
    o = geometry.camera_centre
    oc = o - geometry.ball_centre
    b = d @ oc
    disc = b * b - (oc @ oc - geometry.ball_radius**2)
    hits = disc > 0.0
    dist = -b - np.sqrt(np.where(hits, disc, 0.0))
    hits &= dist > 0.0
    points = o + dist[:, None] * d
    normals = (points - geometry.ball_centre) / geometry.ball_radius
    cos_i = -np.sum(d * normals, axis=1)
    reflected = d + 2.0 * cos_i[:, None] * normals
    rot, origin = light_pose.rotation, light_pose.position
    local_point = (points - origin) @ rot
    local_dir = reflected @ rot
    reaches = hits & (local_point[:, 2] > 0.0) & (local_dir[:, 2] < 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -local_point[:, 2] / local_dir[:, 2]
    u = local_point[:, 0] + s * local_dir[:, 0]
    v = local_point[:, 1] + s * local_dir[:, 1]
    emitted = -local_dir  # from the plane towards the ball
    theta = np.arccos(np.clip(emitted[:, 2], -1.0, 1.0))
    phi = np.arctan2(emitted[:, 1], emitted[:, 0])
    blocked = np.zeros_like(hits)
    if np.any(hits):
        blocked[hits] = housing_blocks(
            np.broadcast_to(o, (hits.sum(), 3)),
            points[hits],
            light_pose,
            geometry.housing_radius,
            geometry.housing_depth,
        )
    valid = reaches & ~blocked
    alpha = np.arccos(np.clip(cos_i, -1.0, 1.0))
    fresnel = conductor_reflectance(cos_i, geometry.n, geometry.k)
    deflection = np.pi - 2.0 * alpha  # between -d and the reflected direction's reverse
    return ChiefRays(
        cols,
        rows,
        hits,
        reaches,
        blocked,
        valid,
        u,
        v,
        theta,
        phi,
        alpha,
        fresnel,
        geometry.cos4(cols, rows),
        points,
        deflection,
    )


def ball_pixel_box(geometry: RigGeometry) -> tuple[int, int, int, int] | None:
    """The pixel box ``(c0, c1, r0, r1)`` (end-exclusive) that holds the ball's image, or None when
    the ball is out of view or its image misses the sensor."""
    rel = geometry.R @ (geometry.ball_centre - geometry.camera_centre)
    if rel[2] <= geometry.ball_radius:
        return None
    dist = np.linalg.norm(rel)
    half = np.arcsin(min(1.0, cast(float, geometry.ball_radius / dist)))  # numpy's stubs: a norm is a floating
    f_px = geometry.K[0, 0]
    centre = geometry.project(geometry.ball_centre[None, :])[0]
    reach = f_px * np.tan(np.arccos(rel[2] / dist) + half) - f_px * np.tan(max(np.arccos(rel[2] / dist) - half, 0))
    radius = max(reach / 2.0, f_px * np.tan(half)) * 1.05 + 3
    c0, c1 = int(max(0, np.floor(centre[0] - radius))), int(min(geometry.width, np.ceil(centre[0] + radius)))
    r0, r1 = int(max(0, np.floor(centre[1] - radius))), int(min(geometry.height, np.ceil(centre[1] + radius)))
    if c1 <= c0 or r1 <= r0:
        return None
    return c0, c1, r0, r1


def grid_stride(box: tuple[int, int, int, int] | None, max_pixels: int | None) -> int:
    """The stride :func:`ball_pixel_grid` takes through ``box`` for at most about ``max_pixels``."""
    if box is None or max_pixels is None:
        return 1
    c0, c1, r0, r1 = box
    return max(1, int(math.ceil(math.sqrt((c1 - c0) * (r1 - r0) / max_pixels))))


def ball_pixel_grid(geometry: RigGeometry, max_pixels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of a box that holds the ball's image (empty if it is out of view).

    With ``max_pixels``, every ``stride``-th column and row only, ``stride`` the smallest whole
    number that leaves at most about that many (the columns and rows that are multiples of it):
    the same pixels as taking them out of the whole box, without making the whole box.
    """
    box = ball_pixel_box(geometry)
    return box_pixels(box, grid_stride(box, max_pixels))


def box_pixels(box: tuple[int, int, int, int] | None, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The columns and rows of ``box`` that are multiples of ``stride``, every pixel's
    coordinates (row by row, as floats); empty for no box."""
    if box is None:
        return np.zeros(0), np.zeros(0)
    c0, c1, r0, r1 = box
    cols = np.arange(-(-c0 // stride) * stride, c1, stride, dtype=float)
    rows = np.arange(-(-r0 // stride) * stride, r1, stride, dtype=float)
    return np.tile(cols, rows.size), np.repeat(rows, cols.size)


def footprint_areas(geometry: RigGeometry, light_pose: Pose, rays: ChiefRays, step: float = 0.5) -> np.ndarray:
    """Area (m²) of each pixel's chief-ray footprint on the light plane (finite differences)."""
    right = trace_pixels(geometry, light_pose, rays.cols + step, rays.rows)
    down = trace_pixels(geometry, light_pose, rays.cols, rays.rows + step)
    du = np.stack([(right.u - rays.u) / step, (right.v - rays.v) / step], axis=-1)
    dv = np.stack([(down.u - rays.u) / step, (down.v - rays.v) / step], axis=-1)
    area = np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0])
    return np.where(rays.valid & right.valid & down.valid, area, np.nan)


def light_pose_at(geometry: RigGeometry, tool_pose: Pose) -> Pose:
    """The light's pose (rig frame) for a tool pose (the arm's base frame):
    ``arm_base ∘ tool ∘ light_to_tool``."""
    light = tool_pose.compose(geometry.light_to_tool)
    return light if geometry.arm_base is None else geometry.arm_base.compose(light)


def specular_points(
    sources: np.ndarray, targets: np.ndarray, centre: np.ndarray, radius: float, iterations: int = 60
) -> np.ndarray:
    """Points on a convex sphere where light from ``sources`` reflects to ``targets``.

    The normal at the reflection point bisects the directions to the source and to the
    target (the law of reflection); iterating that condition converges for a convex
    mirror seen from outside. Shapes broadcast: (..., 3).

    Compiled (:func:`_specular_kernel`): in NumPy a template's 121 paths would take 60 rounds
    of a dozen small array operations, a millisecond of call overhead per template.
    """
    s, t = np.broadcast_arrays(np.asarray(sources, float) - centre, np.asarray(targets, float) - centre)
    shape = s.shape
    found = _specular_kernel(
        np.ascontiguousarray(s.reshape(-1, 3).T),
        np.ascontiguousarray(t.reshape(-1, 3).T),
        float(radius),
        int(iterations),
    )
    return found.T.reshape(shape) + centre


@numba.njit(cache=True, error_model="numpy")
def _specular_kernel(s: np.ndarray, t: np.ndarray, radius: float, iterations: int) -> np.ndarray:
    """:func:`specular_points` about the sphere's centre; ``s``, ``t`` and the result (3, N).

    Every point's update is ``p ← r · unit(unit(s - p) + unit(t - p))``, started from
    ``r · unit(unit(s) + unit(t))``. The loop runs over the points inside each round, so
    that it vectorises (independent square roots and divisions side by side).

    The update of a point depends on nothing but that point, so once every point's new
    value equals its last (a fixed point) or the one before (a two-cycle, which rounding
    can leave), the rest of the rounds would only repeat: the result of all
    ``iterations`` rounds is then read off by their parity, the same to the bit, after
    about 25 of the 60 rounds.
    """
    n = s.shape[1]
    p = np.empty((3, 3, n))  # the last three rounds, in rotation
    for i in range(n):
        ns = math.sqrt(s[0, i] * s[0, i] + s[1, i] * s[1, i] + s[2, i] * s[2, i])
        nt = math.sqrt(t[0, i] * t[0, i] + t[1, i] * t[1, i] + t[2, i] * t[2, i])
        mx, my, mz = s[0, i] / ns + t[0, i] / nt, s[1, i] / ns + t[1, i] / nt, s[2, i] / ns + t[2, i] / nt
        nm = math.sqrt(mx * mx + my * my + mz * mz)
        p[0, 0, i], p[0, 1, i], p[0, 2, i] = radius * (mx / nm), radius * (my / nm), radius * (mz / nm)
    for k in range(1, iterations + 1):
        cur, prev, prev2 = p[k % 3], p[(k - 1) % 3], p[(k - 2) % 3]
        for i in range(n):
            ax, ay, az = s[0, i] - prev[0, i], s[1, i] - prev[1, i], s[2, i] - prev[2, i]
            bx, by, bz = t[0, i] - prev[0, i], t[1, i] - prev[1, i], t[2, i] - prev[2, i]
            na = math.sqrt(ax * ax + ay * ay + az * az)
            nb = math.sqrt(bx * bx + by * by + bz * bz)
            mx, my, mz = ax / na + bx / nb, ay / na + by / nb, az / na + bz / nb
            nm = math.sqrt(mx * mx + my * my + mz * mz)
            cur[0, i], cur[1, i], cur[2, i] = radius * (mx / nm), radius * (my / nm), radius * (mz / nm)
        if k < 2:
            continue
        settled = True
        for i in range(n):
            same = cur[0, i] == prev[0, i] and cur[1, i] == prev[1, i] and cur[2, i] == prev[2, i]
            cycle = cur[0, i] == prev2[0, i] and cur[1, i] == prev2[1, i] and cur[2, i] == prev2[2, i]
            if not (same or cycle):
                settled = False
                break
        if settled:
            # Round ``iterations`` holds round k's value if their difference is even,
            # round k - 1's otherwise (the same value for a fixed point).
            return cur.copy() if (iterations - k) % 2 == 0 else prev.copy()
    return p[iterations % 3].copy()


def light_pose_at_position(run: RunFile, geometry: RigGeometry, index: int) -> Pose:

    measured = run.measured_pose(index)
    return light_pose_at(geometry, measured if measured is not None else run.header.tool_poses[index])


def _aperture_shape(camera: Camera) -> tuple[float, float, float]:
    """The rig camera's ``[camera.aperture]`` as a shape matrix over the circle of its pinhole's
    diameter: an ellipse's axes and angle (the matrix is the same seen from the sensor or from
    the scene, a half turn apart); a circle or a mask, the identity."""
    aperture = camera.aperture
    if aperture.axes_m is None:
        return (1.0, 0.0, 1.0)
    c, s = math.cos(math.radians(aperture.angle_deg)), math.sin(math.radians(aperture.angle_deg))
    a, b = (axis / camera.pinhole_diameter_m for axis in aperture.axes_m)
    return (a * c * c + b * s * s, (a - b) * c * s, a * s * s + b * c * c)

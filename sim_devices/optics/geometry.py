"""The parts a ray meets, in the rig frame: the camera's sensor and aperture, the mirrored
ball (a conductor, with its Fresnel reflectance) and the light's plane with its housing; and
the exact trace of a batch of rays through them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivers.contracts.rig import Rig
from drivers.pose import Pose


@dataclass(frozen=True)
class CameraOptics:
    """Pinhole or thin-lens camera in OpenCV conventions (``x_cam = R X + t``)."""

    rotation: np.ndarray  # rig -> camera
    centre: np.ndarray  # pinhole / lens centre in the rig frame
    sensor_distance: float
    pitch: float
    cx: float
    cy: float
    width: int
    height: int
    aperture_radius: float
    focus_distance: float | None
    wavelengths: np.ndarray

    @classmethod
    def from_rig(cls, rig: Rig) -> CameraOptics:
        cam = rig.camera
        rotation, _ = cam.pose.extrinsics()
        cx, cy = cam.principal_point
        return cls(
            rotation=rotation,
            centre=cam.centre(),
            sensor_distance=cam.sensor_distance_m,
            pitch=cam.pixel_pitch_m,
            cx=cx,
            cy=cy,
            width=cam.width,
            height=cam.height,
            aperture_radius=cam.aperture_diameter_m / 2.0,
            focus_distance=cam.thin_lens.focus_distance_m if cam.thin_lens else None,
            wavelengths=np.asarray(cam.channel_wavelengths_m, dtype=float),
        )

    def rays(
        self, col: np.ndarray, row: np.ndarray, ax: np.ndarray, ay: np.ndarray
    ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
        """Rays from sensor points (pixel coordinates) through aperture points (metres).

        Returns origins and unit directions in the rig frame, and the ``cos⁴β`` factor of
        the sensor-side segment (β its angle to the optical axis).
        """
        f = self.sensor_distance
        sx = (col - self.cx) * self.pitch  # the real sensor sits at (-sx, -sy, -f)
        sy = (row - self.cy) * self.pitch
        cos_beta = f / np.sqrt((ax + sx) ** 2 + (ay + sy) ** 2 + f * f)
        if self.focus_distance is None:  # pinhole: straight on from sensor through aperture
            dx, dy, dz = ax + sx, ay + sy, np.full_like(sx, f)
        else:  # thin lens: towards the sensor point's conjugate on the focus plane
            scale = self.focus_distance / f
            dx, dy, dz = sx * scale - ax, sy * scale - ay, np.full_like(sx, self.focus_distance)
        r = self.rotation  # camera -> rig is r.T
        ox = self.centre[0] + r[0, 0] * ax + r[1, 0] * ay
        oy = self.centre[1] + r[0, 1] * ax + r[1, 1] * ay
        oz = self.centre[2] + r[0, 2] * ax + r[1, 2] * ay
        wx = r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz
        wy = r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz
        wz = r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz
        norm = np.sqrt(wx * wx + wy * wy + wz * wz)
        return (ox, oy, oz), (wx / norm, wy / norm, wz / norm), cos_beta**4


@dataclass(frozen=True)
class Mirror:
    centre: np.ndarray
    radius: float
    n: np.ndarray
    k: np.ndarray

    @classmethod
    def from_rig(cls, rig: Rig) -> Mirror:
        b = rig.ball
        return cls(np.asarray(b.centre_m, float), b.radius_m, np.asarray(b.n, float), np.asarray(b.k, float))


@dataclass(frozen=True)
class LightPlane:
    """The light's frame at one position, and its opaque housing behind the plane."""

    rotation: np.ndarray  # columns: light axes in the rig frame
    origin: np.ndarray
    housing_radius: float
    housing_depth: float

    @classmethod
    def at(cls, rig: Rig, light_pose: Pose) -> LightPlane:
        return cls(
            light_pose.rotation,
            light_pose.position,
            rig.light.housing_radius_m,
            rig.light.housing_depth_m,
        )

    def to_local(
        self, px: np.ndarray, py: np.ndarray, pz: np.ndarray, vx: np.ndarray, vy: np.ndarray, vz: np.ndarray
    ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Point and direction from the rig frame into the light frame."""
        r, o = self.rotation, self.origin
        qx, qy, qz = px - o[0], py - o[1], pz - o[2]
        lp = (
            r[0, 0] * qx + r[1, 0] * qy + r[2, 0] * qz,
            r[0, 1] * qx + r[1, 1] * qy + r[2, 1] * qz,
            r[0, 2] * qx + r[1, 2] * qy + r[2, 2] * qz,
        )
        lv = (
            r[0, 0] * vx + r[1, 0] * vy + r[2, 0] * vz,
            r[0, 1] * vx + r[1, 1] * vy + r[2, 1] * vz,
            r[0, 2] * vx + r[1, 2] * vy + r[2, 2] * vz,
        )
        return lp, lv

    def blocks_segment(self, start: Sequence[np.ndarray], end: Sequence[np.ndarray]) -> np.ndarray:
        """True where the segment ``start → end`` (rig frame) passes through the housing."""
        if self.housing_radius <= 0.0:
            return np.zeros(np.shape(start[0]), dtype=bool)
        (ax, ay, az), (dx, dy, dz) = self.to_local(
            start[0], start[1], start[2], end[0] - start[0], end[1] - start[1], end[2] - start[2]
        )
        # Clip the segment (parameter s in [0, 1]) to the slab -depth <= z <= 0 ...
        with np.errstate(divide="ignore", invalid="ignore"):
            s1 = (-self.housing_depth - az) / dz
            s2 = (0.0 - az) / dz
        lo = np.where(
            np.abs(dz) > 1e-15, np.minimum(s1, s2), np.where((az >= -self.housing_depth) & (az <= 0), -np.inf, np.inf)
        )
        hi = np.where(
            np.abs(dz) > 1e-15, np.maximum(s1, s2), np.where((az >= -self.housing_depth) & (az <= 0), np.inf, -np.inf)
        )
        lo, hi = np.maximum(lo, 0.0), np.minimum(hi, 1.0)
        # ... then to the infinite cylinder x² + y² <= r².
        a = dx * dx + dy * dy
        b = 2.0 * (ax * dx + ay * dy)
        c = ax * ax + ay * ay - self.housing_radius**2
        disc = b * b - 4.0 * a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            c1 = np.where(a > 1e-30, (-b - root) / (2.0 * a), np.where(c <= 0, -np.inf, np.inf))
            c2 = np.where(a > 1e-30, (-b + root) / (2.0 * a), np.where(c <= 0, np.inf, -np.inf))
        inside_cyl = (disc >= 0.0) | (a <= 1e-30)
        return inside_cyl & (np.maximum(lo, c1) <= np.minimum(hi, c2))


def fresnel_conductor(cos_i: np.ndarray, n: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a conductor of index ``n + ik``.

    Parameters
    ----------
    cos_i : ndarray, shape (N,)
        Cosine of the angle of incidence.
    n, k : ndarray, shape (C,)
        Refractive index and extinction coefficient per channel.

    Returns
    -------
    ndarray, shape (N, C)
        ``(|r_s|² + |r_p|²) / 2`` from the complex Fresnel equations (Born & Wolf, §14.4).
    """
    eta = (np.asarray(n) + 1j * np.asarray(k))[None, :]
    ci = np.clip(cos_i, 0.0, 1.0)[:, None]
    si2 = 1.0 - ci * ci
    ct = np.sqrt(1.0 - si2 / (eta * eta))
    rs = (ci - eta * ct) / (ci + eta * ct)
    rp = (eta * ci - ct) / (eta * ci + ct)
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


@dataclass
class Trace:
    """Exact trace of a batch of rays: camera → ball → light plane."""

    valid: np.ndarray
    u: np.ndarray
    v: np.ndarray
    theta: np.ndarray
    phi: np.ndarray
    fresnel: np.ndarray  # (N, 3)
    cos4: np.ndarray


def trace(
    camera: CameraOptics,
    mirror: Mirror,
    plane: LightPlane,
    col: np.ndarray,
    row: np.ndarray,
    ax: np.ndarray,
    ay: np.ndarray,
    *,
    fresnel: bool = True,
) -> Trace:
    """Trace rays given by sensor point (pixels) and aperture point (metres)."""
    (ox, oy, oz), (dx, dy, dz), cos4 = camera.rays(col, row, ax, ay)
    c = mirror.centre
    qx, qy, qz = ox - c[0], oy - c[1], oz - c[2]
    b = qx * dx + qy * dy + qz * dz
    disc = b * b - (qx * qx + qy * qy + qz * qz - mirror.radius**2)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    valid = (disc > 0.0) & (t > 0.0)
    sx, sy, sz = ox + t * dx, oy + t * dy, oz + t * dz
    nx, ny, nz = (sx - c[0]) / mirror.radius, (sy - c[1]) / mirror.radius, (sz - c[2]) / mirror.radius
    cos_i = -(dx * nx + dy * ny + dz * nz)
    rx, ry, rz = dx + 2.0 * cos_i * nx, dy + 2.0 * cos_i * ny, dz + 2.0 * cos_i * nz
    valid &= ~plane.blocks_segment((ox, oy, oz), (sx, sy, sz))
    (px, py, pz), (vx, vy, vz) = plane.to_local(sx, sy, sz, rx, ry, rz)
    # The emitting face looks along +z: only rays arriving from the front reach it.
    valid &= (pz > 0.0) & (vz < 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -pz / vz
    u, v = px + s * vx, py + s * vy
    theta = np.arccos(np.clip(-vz, -1.0, 1.0))
    phi = np.arctan2(-vy, -vx)
    f = fresnel_conductor(cos_i, mirror.n, mirror.k) if fresnel else np.ones((np.size(cos_i), 1))
    return Trace(valid, u, v, theta, phi, f, cos4)

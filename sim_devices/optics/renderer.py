"""The mirrored ball as the camera sees it: the renderer (see :mod:`sim_devices.optics` for the
physics and the sampling of each emitter's pre-image)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import ArrayLike

from drivers.contracts.rig import Rig
from drivers.pose import Pose
from sim_devices.lights import Emitter, TruthLight
from sim_devices.optics.aperture import ApertureShape
from sim_devices.optics.diffraction import apply_diffraction
from sim_devices.optics.fresnel import BAND_SAMPLES, PathCurvature
from sim_devices.optics.geometry import CameraOptics, LightPlane, Mirror, Trace, fresnel_conductor, trace
from sim_devices.optics.point_spread import FresnelBlur
from sim_devices.optics.sampling import subpixel_pattern, unit_disc_samples

#: With the Fresnel point spread the ray tracing draws the sharp image: the chief rays, through an
#: aperture this fraction of the pinhole's radius (its geometric blur, ~0.002 px, is negligible).
CHIEF_RAY_APERTURE = 1e-4
POINT_SPREADS = ("geometric-airy", "fresnel")


@dataclass
class RenderStats:
    pixels_on_ball: int = 0
    rays_traced: int = 0
    rim_hit_fraction: float = 0.0  # hits in the outer rim of the sampled ellipse (should be 0)
    per_emitter_pixels: dict = field(default_factory=dict)
    # Fresnel: each emitter's image distances (m) along the incident wave's principal axes.
    per_emitter_image_distance: dict = field(default_factory=dict)


def environment_rgb(radiance: ArrayLike) -> np.ndarray:
    """A uniform environment's radiance as (R, G, B): a number or one per channel, finite, ≥ 0."""
    env = np.broadcast_to(np.asarray(radiance, dtype=float), (3,)).copy()
    if not np.all(np.isfinite(env)) or np.any(env < 0):
        raise ValueError(f"environment_radiance must be finite and >= 0, got {radiance!r}")
    return env


@dataclass
class Rendering:
    """Expected electron rate per second per channel (before noise and the mosaic)."""

    rate: np.ndarray  # (3, H, W) float64
    stats: RenderStats


class MirrorBallRenderer:
    """Render the mirrored ball as the camera sees it with the light at a given pose.

    Parameters
    ----------
    rig : Rig
        Camera, ball and light housing.
    truth : TruthLight
        The emitters on the light plane.
    subpixel_per_side : int
        The pixel area is sampled on a jittered ``n × n`` grid.
    aperture_samples : int
        Rays per sub-pixel sample inside each emitter's pre-image ellipse.
    wide_aperture_samples : int
        Rays per sub-pixel sample over the whole aperture for emitters wider than it.
    diffraction : bool
        Blur with the aperture's diffraction (``point_spread``); without it, the geometric image.
    point_spread : {"geometric-airy", "fresnel"}, optional
        The rig's ``camera.point_spread`` by default.
        ``geometric-airy``: rays sampled over the whole aperture (its geometric shadow), then
        the Airy pattern of each channel's wavelength. ``fresnel``: the chief rays only (the
        sharp image), each emitter's then convolved with the Fresnel point spread of its own
        path (:mod:`~sim_devices.optics.point_spread`) over each channel's band.
    band_samples : int
        Fresnel: wavelengths a channel's band is integrated over.
    seed : int
        Seed of the sample jitter.
    environment_radiance : float or (R, G, B)
        Uniform radiance of the surroundings the ball reflects (0: a dark room, the
        default). Used for calibration images: the ball then shows as a bright disc.
    environment_aperture_samples : int
        Rays per sub-pixel sample over the whole aperture for pixels near an edge of the
        environment's image (the silhouette, the housing).
    """

    ellipse_scale = 1.5
    sensor_splat_max_px = 40.0

    def __init__(
        self,
        rig: Rig,
        truth: TruthLight | None,
        *,
        subpixel_per_side: int = 2,
        aperture_samples: int = 48,
        wide_aperture_samples: int = 16,
        diffraction: bool = True,
        point_spread: str | None = None,
        band_samples: int = BAND_SAMPLES,
        seed: int = 0,
        chunk_rays: int = 2_000_000,
        environment_radiance: float | tuple[float, float, float] = 0.0,
        environment_aperture_samples: int = 32,
    ):
        point_spread = rig.camera.point_spread if point_spread is None else point_spread
        if point_spread not in POINT_SPREADS:
            raise ValueError(f"point_spread must be one of {', '.join(POINT_SPREADS)}, got {point_spread!r}")
        self.rig = rig
        self.truth = truth
        self.camera = CameraOptics.from_rig(rig)
        self.fresnel: FresnelBlur | None = None
        if diffraction and point_spread == "fresnel":
            self.fresnel = FresnelBlur(rig.camera, ApertureShape.from_rig(rig.camera), band_samples)
            self.camera = replace(self.camera, aperture_radius=CHIEF_RAY_APERTURE * self.camera.aperture_radius)
        self.mirror = Mirror.from_rig(rig)
        self.subpixel = subpixel_pattern(subpixel_per_side)
        self.subpixel_cell = 1.0 / subpixel_per_side
        self.aperture_samples = aperture_samples
        self.wide_aperture_samples = wide_aperture_samples
        self.diffraction = diffraction
        self.rng = np.random.default_rng(seed)
        self.chunk_rays = chunk_rays
        self.sensitivity = rig.camera.sensitivity_e_per_s
        self.set_environment(environment_radiance)
        self.environment_aperture_samples = environment_aperture_samples

    def set_environment(self, radiance: ArrayLike) -> None:
        """The uniform environment's radiance: a number, or one per channel (R, G, B)."""
        self.environment = environment_rgb(radiance)

    # Pixels whose chief ray meets the ball ----------------------------------------------------
    def _ball_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        cam = self.camera
        rel = cam.rotation @ (self.mirror.centre - cam.centre)
        dist = float(np.linalg.norm(rel))
        half = math.asin(min(1.0, self.mirror.radius / dist))
        axis = rel / dist
        # Project the silhouette cone's rim to bound the ball's image.
        helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        a = np.linspace(0, 2 * math.pi, 90, endpoint=False)[:, None]
        rim = math.cos(half) * axis + math.sin(half) * (np.cos(a) * e1 + np.sin(a) * e2)
        fpx = cam.sensor_distance / cam.pitch
        cols = cam.cx + fpx * rim[:, 0] / rim[:, 2]
        rows = cam.cy + fpx * rim[:, 1] / rim[:, 2]
        c0, c1 = max(0, int(cols.min()) - 2), min(cam.width, int(math.ceil(cols.max())) + 3)
        r0, r1 = max(0, int(rows.min()) - 2), min(cam.height, int(math.ceil(rows.max())) + 3)
        rr, cc = np.mgrid[r0:r1, c0:c1]
        return cc.ravel().astype(float), rr.ravel().astype(float)

    def render(self, light_pose: Pose) -> Rendering:
        """Expected electron rates with the light at ``light_pose`` (rig frame)."""
        cam, stats = self.camera, RenderStats()
        plane = LightPlane.at(self.rig, light_pose)
        rate = np.zeros((3, cam.height * cam.width))
        # Fresnel: the sharp image of each group of emitters that share a point spread, by its key.
        layers: dict[tuple, tuple[PathCurvature, np.ndarray]] = {}

        def layer(path: PathCurvature | None) -> np.ndarray:
            if self.fresnel is None or path is None:
                return rate
            rounded = self.fresnel.rounded(path)
            return layers.setdefault(rounded.key, (rounded, np.zeros_like(rate)))[1]

        lit_room = bool(np.any(self.environment > 0))
        if lit_room:
            target = layer(self._environment_path())
            target += self._render_environment(plane, stats)
        col, row = self._ball_pixels()
        zero = np.zeros_like(col)
        chief = trace(cam, self.mirror, plane, col, row, zero, zero, fresnel=False)
        keep = chief.valid
        col, row = col[keep], row[keep]
        uv0 = np.column_stack([chief.u[keep], chief.v[keep]])
        stats.pixels_on_ball = int(keep.sum())
        stats.rays_traced += chief.valid.size
        if col.size == 0 and not lit_room:
            return Rendering(rate.reshape(3, cam.height, cam.width), stats)
        if col.size:

            def emitter_layer(emitter: Emitter) -> np.ndarray:
                if self.fresnel is None:
                    return rate
                path = self._emitter_path(plane, emitter, col, row, uv0) or self._environment_path()
                name = emitter.name or str(len(stats.per_emitter_image_distance))
                stats.per_emitter_image_distance[name] = path.image_distances()[:2]
                return layer(path)

            self._render_emitters(plane, stats, emitter_layer, col, row, uv0)

        rate = rate.reshape(3, cam.height, cam.width) * self.sensitivity
        if self.fresnel is not None:
            for path, sharp in layers.values():
                rate += self.fresnel.blur(sharp.reshape(rate.shape) * self.sensitivity, path)
        elif self.diffraction:
            for ch in range(3):
                rate[ch] = apply_diffraction(
                    rate[ch], cam.pitch, 2 * cam.aperture_radius, cam.sensor_distance, cam.wavelengths[ch]
                )
            np.clip(rate, 0.0, None, out=rate)
        return Rendering(rate, stats)

    def _render_emitters(
        self,
        plane: LightPlane,
        stats: RenderStats,
        layer_of: Callable[[Emitter], np.ndarray],
        col: np.ndarray,
        row: np.ndarray,
        uv0: np.ndarray,
    ) -> None:
        """Add each emitter's image to ``layer_of(emitter)``, a (3, H·W) rate array."""
        cam = self.camera
        # Affine map of aperture offset and sensor offset onto the light plane, per pixel.
        h_a = 0.5 * cam.aperture_radius
        ja, ok_a = self._jacobian_aperture(plane, col, row, np.zeros_like(col), np.zeros_like(col), uv0, h_a)
        jd, ok_d = self._jacobian_sensor(plane, col, row, np.zeros_like(col), np.zeros_like(col), uv0)
        stats.rays_traced += 4 * col.size
        ok = ok_a & ok_d
        col, row, uv0, ja, jd = col[ok], row[ok], uv0[ok], ja[ok], jd[ok]

        rim_hits = total_hits = 0
        for emitter in self.truth.emitters if self.truth is not None else []:
            contrib, pix, rim, hits, rays = self._render_emitter(plane, emitter, col, row, uv0, ja, jd)
            stats.rays_traced += rays
            stats.per_emitter_pixels[emitter.name or str(len(stats.per_emitter_pixels))] = int(np.unique(pix).size)
            rim_hits += rim
            total_hits += hits
            if pix.size:
                rate = layer_of(emitter)
                for ch in range(3):
                    rate[ch] += np.bincount(pix, weights=contrib[:, ch], minlength=rate.shape[1])
        stats.rim_hit_fraction = rim_hits / total_hits if total_hits else 0.0

    # --- the uniform environment ------------------------------------------------------------
    def _environment_blur_px(self, plane: LightPlane) -> float:
        """An upper bound of the radius (pixels) of any scene point's blur on the sensor.

        Everything the environment pass can see lies between the nearest of the ball's
        front and the light's housing, and the ball's far side (virtual images of the
        surroundings lie inside the ball). A pinhole blurs a point at distance z into a
        disc of radius ``a (1 + f/z)``; a thin lens focused at ``z_f`` into ``a f |1/z - 1/z_f|``.
        """
        cam = self.camera
        dist = float(np.linalg.norm(self.mirror.centre - cam.centre))
        z_near = dist - self.mirror.radius
        if plane.housing_radius > 0:
            to_light = float(np.linalg.norm(plane.origin - cam.centre))
            z_near = min(z_near, to_light - plane.housing_radius - plane.housing_depth)
        z_near = max(z_near, 0.2 * (dist - self.mirror.radius), 1e-3)
        z_far = dist + self.mirror.radius
        a, f = cam.aperture_radius, cam.sensor_distance
        if cam.focus_distance is None:
            blur = a * (1.0 + f / z_near)
        else:
            blur = a * f * max(abs(1.0 / z - 1.0 / cam.focus_distance) for z in (z_near, z_far))
        return blur / cam.pitch

    def _environment_rays(
        self, plane: LightPlane, col: np.ndarray, row: np.ndarray, ax: np.ndarray, ay: np.ndarray
    ) -> np.ndarray:
        """Per ray: the environment's ``F(α) · cos⁴β`` (N, 3), 0 where it is not seen."""
        (ox, oy, oz), (dx, dy, dz), cos4 = self.camera.rays(col, row, ax, ay)
        c, radius = self.mirror.centre, self.mirror.radius
        qx, qy, qz = ox - c[0], oy - c[1], oz - c[2]
        b = qx * dx + qy * dy + qz * dz
        disc = b * b - (qx * qx + qy * qy + qz * qz - radius**2)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        seen = (disc > 0.0) & (t > 0.0)
        sx, sy, sz = ox + t * dx, oy + t * dy, oz + t * dz
        nx, ny, nz = (sx - c[0]) / radius, (sy - c[1]) / radius, (sz - c[2]) / radius
        cos_i = -(dx * nx + dy * ny + dz * nz)
        rx, ry, rz = dx + 2.0 * cos_i * nx, dy + 2.0 * cos_i * ny, dz + 2.0 * cos_i * nz
        if plane.housing_radius > 0:
            seen &= ~plane.blocks_segment((ox, oy, oz), (sx, sy, sz))  # the housing hides the ball
            far = 100.0  # metres: the reflected ray, far beyond the rig
            seen &= ~plane.blocks_segment((sx, sy, sz), (sx + far * rx, sy + far * ry, sz + far * rz))
        # F(cos α) from a fine table of the exact formula (linear in cos α at grazing,
        # smooth elsewhere: interpolation error below 1e-8), for speed.
        grid, table = self._fresnel_table()
        c = np.clip(cos_i, 0.0, 1.0)
        value = np.stack([np.interp(c, grid, table[:, ch]) for ch in range(table.shape[1])], axis=-1)
        return np.where(seen[:, None], value * cos4[:, None], 0.0)

    def _fresnel_table(self) -> tuple[np.ndarray, np.ndarray]:
        if getattr(self, "_fresnel_lut", None) is None:
            grid = np.linspace(0.0, 1.0, 16385)
            self._fresnel_lut = (grid, fresnel_conductor(grid, self.mirror.n, self.mirror.k))
        return self._fresnel_lut

    def _render_environment(self, plane: LightPlane, stats: RenderStats) -> np.ndarray:
        """Unscaled rate (3, H·W) of the uniform environment reflected by the ball."""
        cam = self.camera
        out = np.zeros((3, cam.height * cam.width))
        margin = int(math.ceil(1.25 * self._environment_blur_px(plane) + 2.0))
        col, row = self._ball_pixels()
        if col.size == 0:
            return out
        c0, c1 = max(0, int(col.min()) - margin), min(cam.width, int(col.max()) + margin + 1)
        r0, r1 = max(0, int(row.min()) - margin), min(cam.height, int(row.max()) + margin + 1)
        rr, cc = np.mgrid[r0:r1, c0:c1]
        zero = np.zeros(cc.size)
        chief = self._environment_rays(plane, cc.ravel().astype(float), rr.ravel().astype(float), zero, zero)
        seen = (chief[:, 1] > 0).reshape(rr.shape).astype(np.uint8)
        stats.rays_traced += cc.size
        # Pixels within the blur radius of a differently classified pixel straddle an edge.
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        near_edge = cv2.dilate(seen, kernel, borderType=cv2.BORDER_REPLICATE) != cv2.erode(
            seen, kernel, borderType=cv2.BORDER_REPLICATE
        )
        interior = (seen.astype(bool) & ~near_edge).ravel()
        edge = near_edge.ravel()
        flat = (rr * cam.width + cc).ravel()
        for mask, ndisc in ((interior, 1), (edge, self.environment_aperture_samples)):
            pix = flat[mask]
            pcol, prow = cc.ravel()[mask].astype(float), rr.ravel()[mask].astype(float)
            value, rays = self._environment_pixels(plane, pcol, prow, ndisc)
            stats.rays_traced += rays
            out[:, pix] = value.T * self.environment[:, None]
        return out

    def _environment_pixels(
        self, plane: LightPlane, col: np.ndarray, row: np.ndarray, ndisc: int
    ) -> tuple[np.ndarray, int]:
        """Mean of ``F · cos⁴`` over each pixel's area × the whole aperture (stratified)."""
        ra = self.camera.aperture_radius
        nsub = len(self.subpixel)
        per_pixel = nsub * ndisc
        out = np.zeros((col.size, 3))
        step = max(1, self.chunk_rays // per_pixel)
        for s in range(0, col.size, step):
            sl = slice(s, min(col.size, s + step))
            m = sl.stop - sl.start
            offs = self.subpixel[None] + self.rng.random((m, nsub, 2)) * self.subpixel_cell
            disc = ra * unit_disc_samples(ndisc, (m, nsub), self.rng)
            shape = (m, nsub, ndisc)
            sc = np.broadcast_to((col[sl, None] + offs[..., 0])[:, :, None], shape).ravel()
            sr = np.broadcast_to((row[sl, None] + offs[..., 1])[:, :, None], shape).ravel()
            value = self._environment_rays(plane, sc, sr, disc[..., 0].ravel(), disc[..., 1].ravel())
            out[sl] = value.reshape(m, per_pixel, 3).mean(axis=1)
        return out, col.size * per_pixel

    def _hidden_environment(self, plane: LightPlane, t: Trace, on: np.ndarray) -> np.ndarray:
        """``L_env · F · cos⁴`` (N, 3) for emitter hits outside the housing's face: light of
        the surroundings the emitter hides (already counted by the environment pass)."""
        bare = on & (t.u * t.u + t.v * t.v > plane.housing_radius**2)
        return np.where(bare[:, None], t.fresnel * t.cos4[:, None] * self.environment[None, :], 0.0)

    # --- the Fresnel point spread's path -----------------------------------------------------
    def _emitter_path(
        self, plane: LightPlane, emitter: Emitter, col: np.ndarray, row: np.ndarray, uv0: np.ndarray
    ) -> PathCurvature | None:
        """The optical path about the chief ray onto the emitter's centre (None where it is not
        traced): Newton's method on the exact trace for the sensor point, then the rays'
        magnification ``M = ∂p/∂ρ = −J_p⁻¹ J_ρ`` by central differences (1 % of the pinhole's
        radius, 0.01 px; the image distances are then converged to 1e-4 mm)."""
        cam = self.camera
        q = np.asarray(emitter.centre_m, dtype=float)
        i0 = int(np.argmin(np.linalg.norm(uv0 - q[None, :], axis=1)))
        point = np.array([col[i0], row[i0]])
        h_a, h_p = 0.01 * self.rig.camera.aperture_diameter_m / 2.0, 0.01
        for _ in range(6):
            jacobians = self._central_jacobians(plane, point, h_a, h_p)
            if jacobians is None:
                return None
            ja, jd, uv = jacobians
            step = np.linalg.solve(jd, q - uv)
            point = point + step
            if np.hypot(*step) < 1e-6:
                break
        jacobians = self._central_jacobians(plane, point, h_a, h_p)
        if jacobians is None:
            return None
        ja, jd, _ = jacobians
        sensor = ((point[0] - cam.cx) * cam.pitch, (point[1] - cam.cy) * cam.pitch)
        return PathCurvature.from_rays(-np.linalg.solve(jd, ja), sensor, cam.sensor_distance, cam.pitch)

    def _central_jacobians(
        self, plane: LightPlane, point: np.ndarray, h_a: float, h_p: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(∂(u, v)/∂ρ, ∂(u, v)/∂p, (u, v))`` of the chief ray from sensor ``point`` (pixels), or None."""
        dp = np.array([0, 1, -1, 0, 0, 0, 0, 0, 0]) * h_p
        dq = np.array([0, 0, 0, 1, -1, 0, 0, 0, 0]) * h_p
        ax = np.array([0, 0, 0, 0, 0, 1, -1, 0, 0]) * h_a
        ay = np.array([0, 0, 0, 0, 0, 0, 0, 1, -1]) * h_a
        t = trace(self.camera, self.mirror, plane, point[0] + dp, point[1] + dq, ax, ay, fresnel=False)
        if not np.all(t.valid):
            return None
        uv = np.column_stack([t.u, t.v])
        jd = np.column_stack([uv[1] - uv[2], uv[3] - uv[4]]) / (2.0 * h_p)
        ja = np.column_stack([uv[5] - uv[6], uv[7] - uv[8]]) / (2.0 * h_a)
        return ja, jd, uv[0]

    def _environment_path(self) -> PathCurvature:
        """The surroundings' path: their virtual image at the ball's focal point, half its radius
        behind the apex the camera sees (the paraxial mirror equation), taken on the axis."""
        cam = self.camera
        distance = float(np.linalg.norm(self.mirror.centre - cam.centre)) - 0.5 * self.mirror.radius
        return PathCurvature.on_axis(distance, cam.sensor_distance, cam.pitch)

    # --- local linearisation ------------------------------------------------------------------
    def _jacobian_aperture(
        self,
        plane: LightPlane,
        col: np.ndarray,
        row: np.ndarray,
        ax: np.ndarray,
        ay: np.ndarray,
        uv: np.ndarray,
        h: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        tx = trace(self.camera, self.mirror, plane, col, row, ax + h, ay, fresnel=False)
        ty = trace(self.camera, self.mirror, plane, col, row, ax, ay + h, fresnel=False)
        j = np.empty((col.size, 2, 2))
        j[:, 0, 0], j[:, 1, 0] = (tx.u - uv[:, 0]) / h, (tx.v - uv[:, 1]) / h
        j[:, 0, 1], j[:, 1, 1] = (ty.u - uv[:, 0]) / h, (ty.v - uv[:, 1]) / h
        return j, tx.valid & ty.valid

    def _jacobian_sensor(
        self,
        plane: LightPlane,
        col: np.ndarray,
        row: np.ndarray,
        ax: np.ndarray,
        ay: np.ndarray,
        uv: np.ndarray,
        h: float = 0.25,
    ) -> tuple[np.ndarray, np.ndarray]:
        tx = trace(self.camera, self.mirror, plane, col + h, row, ax, ay, fresnel=False)
        ty = trace(self.camera, self.mirror, plane, col, row + h, ax, ay, fresnel=False)
        j = np.empty((col.size, 2, 2))
        j[:, 0, 0], j[:, 1, 0] = (tx.u - uv[:, 0]) / h, (tx.v - uv[:, 1]) / h
        j[:, 0, 1], j[:, 1, 1] = (ty.u - uv[:, 0]) / h, (ty.v - uv[:, 1]) / h
        return j, tx.valid & ty.valid

    # --- one emitter --------------------------------------------------------------------------
    def _render_emitter(
        self,
        plane: LightPlane,
        emitter: Emitter,
        col: np.ndarray,
        row: np.ndarray,
        uv0: np.ndarray,
        ja: np.ndarray,
        jd: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, int, int, int]:
        cam = self.camera
        ra = cam.aperture_radius
        q = np.asarray(emitter.centre_m, dtype=float)
        rho = emitter.radius_m
        empty = (np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 0, 0, 0)
        sv_a = np.linalg.svd(ja, compute_uv=False)
        distance = np.linalg.norm(uv0 - q[None, :], axis=1)
        # The pixel whose chief ray lands closest to the emitter: its sharp image.
        i0 = int(np.argmin(distance))
        footprint = sv_a[i0, 1] * ra  # the smallest reach of one pixel's rays on the plane
        if distance[i0] > rho + 2.0 * sv_a[i0, 0] * ra + np.linalg.norm(jd[i0]):
            return empty  # the ball never shows this emitter to the camera
        aperture_pre_area = math.pi * (self.ellipse_scale * rho) ** 2 / abs(np.linalg.det(ja[i0]))
        sensor_pre_radius = self.ellipse_scale * rho * np.linalg.svd(np.linalg.inv(jd[i0]), compute_uv=False)[0]
        if aperture_pre_area >= math.pi * ra * ra and sensor_pre_radius < self.sensor_splat_max_px:
            # A focused camera: for a fixed aperture point the emitter's pre-image on the
            # sensor is small, so sample there instead (and splat into pixels).
            return self._sensor_narrow(plane, emitter, col[i0], row[i0], uv0[i0], ja[i0], jd[i0])
        if self.ellipse_scale * rho < footprint:
            # Small emitter: only pixels within the blur disc around its image see it.
            j_inv = np.linalg.inv(ja[i0])
            shift = j_inv @ jd[i0]  # aperture shift per pixel of sensor shift
            sv_shift = np.linalg.svd(shift, compute_uv=False)
            pre_image = self.ellipse_scale * rho * np.linalg.svd(j_inv, compute_uv=False)[0]
            blur_px = 1.15 * (ra + pre_image + sv_shift[0]) / sv_shift[1] + 2.0
            near = np.hypot(col - col[i0], row - row[i0]) <= blur_px
            idx = np.flatnonzero(near)
            a0 = np.einsum("nij,nj->ni", np.linalg.inv(ja[idx]), q[None, :] - uv0[idx])
            return self._narrow(plane, emitter, col[idx], row[idx], a0, uv0[idx], ja[idx])
        # Wide emitter: every pixel whose rays can reach its disc samples the whole aperture.
        reach = rho + 1.5 * sv_a[:, 0] * ra + np.linalg.norm(jd, axis=(1, 2))
        idx = np.flatnonzero(distance <= reach)
        c, p, n = self._wide(plane, emitter, col[idx], row[idx])
        return c, p, 0, 0, n

    def _narrow(
        self,
        plane: LightPlane,
        emitter: Emitter,
        col: np.ndarray,
        row: np.ndarray,
        a0: np.ndarray,
        uv0: np.ndarray,
        ja: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, int, int, int]:
        """Emitter smaller than the aperture's footprint: sample its pre-image ellipse."""
        ra, rho = self.camera.aperture_radius, emitter.radius_m
        col, row, a, j, jd = self._aim_at_emitter(plane, emitter, col, row, a0, uv0, ja)
        if col.size == 0:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 0, 0, 0
        j_inv = np.linalg.inv(j)
        shift_per_px = -np.einsum("nij,njk->nik", j_inv, jd)  # aperture shift per pixel offset
        radius = self.ellipse_scale * rho
        ellipse_area = math.pi * radius**2 * np.abs(np.linalg.det(j_inv))
        # Keep pixels whose ellipse can reach the aperture from some point of the pixel.
        reach = radius * np.linalg.svd(j_inv, compute_uv=False)[:, 0] + 0.75 * np.linalg.norm(shift_per_px, axis=(1, 2))
        keep = np.linalg.norm(a, axis=1) <= ra + reach
        col, row, a, j_inv, shift_per_px, ellipse_area = (
            x[keep] for x in (col, row, a, j_inv, shift_per_px, ellipse_area)
        )
        if col.size == 0:  # the emitter's image falls outside the sensor
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 0, 0, 0
        return self._sample_ellipses(plane, emitter, col, row, a, j_inv, shift_per_px, ellipse_area)

    def _aim_at_emitter(
        self,
        plane: LightPlane,
        emitter: Emitter,
        col: np.ndarray,
        row: np.ndarray,
        a0: np.ndarray,
        uv0: np.ndarray,
        ja: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Newton's method on the exact trace: per pixel, the aperture point whose chief ray lands
        on the emitter's centre, with the aperture and sensor Jacobians there.

        Returns the pixels where every trace of the last step was valid, as
        ``(col, row, aperture point, aperture Jacobian, sensor Jacobian)``.
        """
        cam, ra = self.camera, self.camera.aperture_radius
        q = np.asarray(emitter.centre_m, dtype=float)
        a = a0.copy()
        j = ja.copy()
        good = np.ones(col.size, dtype=bool)
        h = 0.02 * ra
        for _ in range(4):
            limit = 4.0 * ra
            norm = np.linalg.norm(a, axis=1, keepdims=True)
            a = np.where(norm > limit, a * limit / np.maximum(norm, 1e-30), a)
            t = trace(cam, self.mirror, plane, col, row, a[:, 0], a[:, 1], fresnel=False)
            uv = np.column_stack([t.u, t.v])
            jn, okj = self._jacobian_aperture(plane, col, row, a[:, 0], a[:, 1], uv, h)
            ok = t.valid & okj
            j = np.where(ok[:, None, None], jn, j)
            step = np.einsum(
                "nij,nj->ni",
                np.linalg.inv(j),
                q[None, :] - np.where(ok[:, None], uv, uv0 + np.einsum("nij,nj->ni", ja, a)),
            )
            a = a + step
            good = ok
        jd, okd = self._jacobian_sensor(plane, col, row, a[:, 0], a[:, 1], q[None, :] + np.zeros_like(a))
        good &= okd
        return col[good], row[good], a[good], j[good], jd[good]

    def _sample_ellipses(
        self,
        plane: LightPlane,
        emitter: Emitter,
        col: np.ndarray,
        row: np.ndarray,
        a: np.ndarray,
        j_inv: np.ndarray,
        shift_per_px: np.ndarray,
        ellipse_area: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, int, int, int]:
        """Trace stratified samples of each pixel's pre-image ellipse (in chunks of rays).

        Returns ``(contribution per pixel (N, 3), pixel index, rim hits, hits, rays)``.
        """
        cam, ra, rho = self.camera, self.camera.aperture_radius, emitter.radius_m
        radius = self.ellipse_scale * rho
        npx = col.size
        nsub, ndisc = len(self.subpixel), self.aperture_samples
        per_pixel = nsub * ndisc
        weight = ellipse_area / (math.pi * ra * ra) / per_pixel
        pixel_index = row.astype(np.int64) * cam.width + col.astype(np.int64)
        contrib_all, pix_all = [], []
        rim = hits = 0
        step = max(1, self.chunk_rays // per_pixel)
        for s in range(0, npx, step):
            sl = slice(s, min(npx, s + step))
            m = sl.stop - sl.start
            jitter = self.rng.random((m, nsub, 2)) * self.subpixel_cell
            offs = self.subpixel[None, :, :] + jitter  # (m, nsub, 2) pixel offsets in [-0.5, 0.5)
            centres = a[sl, None, :] + np.einsum("nij,nsj->nsi", shift_per_px[sl], offs)
            disc = unit_disc_samples(ndisc, (m, nsub), self.rng)  # (m, nsub, ndisc, 2)
            pts = centres[:, :, None, :] + radius * np.einsum("nij,nskj->nski", j_inv[sl], disc)
            ax, ay = pts[..., 0].ravel(), pts[..., 1].ravel()
            sc = np.broadcast_to((col[sl, None] + offs[..., 0])[:, :, None], pts.shape[:3]).ravel()
            sr = np.broadcast_to((row[sl, None] + offs[..., 1])[:, :, None], pts.shape[:3]).ravel()
            in_aperture = ax * ax + ay * ay <= ra * ra
            t = trace(cam, self.mirror, plane, sc[in_aperture], sr[in_aperture], ax[in_aperture], ay[in_aperture])
            du, dv = t.u - emitter.centre_m[0], t.v - emitter.centre_m[1]
            on = t.valid & (du * du + dv * dv <= rho * rho)
            value = np.zeros((ax.size, 3))
            value[in_aperture] = np.where(
                on[:, None],
                (emitter.radiance(t.theta, t.phi) * t.cos4)[:, None]
                * t.fresnel
                * np.asarray(emitter.spectrum)[None, :],
                0.0,
            )
            if np.any(self.environment > 0):
                value[in_aperture] -= self._hidden_environment(plane, t, on)
            # Rim check: hits in the outer third of the sampled ellipse's radius would mean
            # the ellipse may be too small to hold the whole pre-image.
            disc_r = np.linalg.norm(disc, axis=-1).ravel()
            rim += int(np.count_nonzero(on & (disc_r[in_aperture] > 0.9)))
            hits += int(np.count_nonzero(on))
            contrib_all.append(value.reshape(m, per_pixel, 3).sum(axis=1) * weight[sl, None])
            pix_all.append(pixel_index[sl])
        return np.concatenate(contrib_all), np.concatenate(pix_all), rim, hits, npx * per_pixel

    def _sensor_narrow(
        self,
        plane: LightPlane,
        emitter: Emitter,
        col0: np.ndarray,
        row0: np.ndarray,
        uv_chief: np.ndarray,
        ja: np.ndarray,
        jd: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, int, int, int]:
        """Emitter whose image, for a fixed aperture point, is small on the sensor.

        Stratified aperture points; for each, Newton's method finds the sensor point whose
        ray lands on the emitter's centre, and samples fill an ellipse 1.5 times the
        emitter's pre-image around it. Each sample adds to the pixel it falls in.
        """
        cam, ra, rho = self.camera, self.camera.aperture_radius, emitter.radius_m
        q = np.asarray(emitter.centre_m, dtype=float)
        n_ap = self.aperture_samples * len(self.subpixel)
        a = ra * unit_disc_samples(n_ap, (), self.rng)
        ax, ay = a[:, 0], a[:, 1]
        jd_inv = np.linalg.inv(jd)
        start = np.array([col0, row0]) + (jd_inv @ (q[:, None] - uv_chief[:, None] - ja @ a.T)).T
        sc, sr = start[:, 0].copy(), start[:, 1].copy()
        j = np.broadcast_to(jd, (n_ap, 2, 2)).copy()
        for _ in range(4):
            t = trace(cam, self.mirror, plane, sc, sr, ax, ay, fresnel=False)
            uv = np.column_stack([t.u, t.v])
            jn, okj = self._jacobian_sensor(plane, sc, sr, ax, ay, uv)
            ok = t.valid & okj
            j = np.where(ok[:, None, None], jn, j)
            step = np.einsum("nij,nj->ni", np.linalg.inv(j), q[None, :] - uv)
            sc, sr = np.where(ok, sc + step[:, 0], sc), np.where(ok, sr + step[:, 1], sr)
        j_inv = np.linalg.inv(j)
        radius = self.ellipse_scale * rho
        area_px = math.pi * radius**2 * np.abs(np.linalg.det(j_inv))
        per_point = int(np.clip(np.ceil(16.0 * area_px.max()), 32, 4096))
        disc = unit_disc_samples(per_point, (n_ap,), self.rng)
        pts = np.stack([sc, sr], axis=-1)[:, None, :] + radius * np.einsum("nij,nkj->nki", j_inv, disc)
        px, py = pts[..., 0].ravel(), pts[..., 1].ravel()
        axs, ays = np.repeat(ax, per_point), np.repeat(ay, per_point)
        t = trace(cam, self.mirror, plane, px, py, axs, ays)
        du, dv = t.u - q[0], t.v - q[1]
        on = t.valid & (du * du + dv * dv <= rho * rho)
        on &= (px > -0.5) & (px < cam.width - 0.5) & (py > -0.5) & (py < cam.height - 0.5)
        weight = np.repeat(area_px / (n_ap * per_point), per_point)
        value = (emitter.radiance(t.theta[on], t.phi[on]) * t.cos4[on] * weight[on])[:, None]
        value = value * t.fresnel[on] * np.asarray(emitter.spectrum)[None, :]
        if np.any(self.environment > 0):
            value -= self._hidden_environment(plane, t, on)[on] * weight[on, None]
        pixel = np.rint(py[on]).astype(np.int64) * cam.width + np.rint(px[on]).astype(np.int64)
        disc_r = np.linalg.norm(disc, axis=-1).ravel()
        rim = int(np.count_nonzero(disc_r[on] > 0.9))
        return value, pixel, rim, int(on.sum()), int(px.size + 8 * n_ap)

    def _wide(
        self, plane: LightPlane, emitter: Emitter, col: np.ndarray, row: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Emitter wider than the aperture's footprint: sample the whole aperture."""
        cam, ra = self.camera, self.camera.aperture_radius
        npx = col.size
        nsub, ndisc = len(self.subpixel), self.wide_aperture_samples
        per_pixel = nsub * ndisc
        pixel_index = row.astype(np.int64) * cam.width + col.astype(np.int64)
        out = []
        step = max(1, self.chunk_rays // per_pixel)
        for s in range(0, npx, step):
            sl = slice(s, min(npx, s + step))
            m = sl.stop - sl.start
            offs = self.subpixel[None] + self.rng.random((m, nsub, 2)) * self.subpixel_cell
            disc = ra * unit_disc_samples(ndisc, (m, nsub), self.rng)
            shape = (m, nsub, ndisc)
            ax, ay = disc[..., 0].ravel(), disc[..., 1].ravel()
            sc = np.broadcast_to((col[sl, None] + offs[..., 0])[:, :, None], shape).ravel()
            sr = np.broadcast_to((row[sl, None] + offs[..., 1])[:, :, None], shape).ravel()
            t = trace(cam, self.mirror, plane, sc, sr, ax, ay)
            du, dv = t.u - emitter.centre_m[0], t.v - emitter.centre_m[1]
            on = t.valid & (du * du + dv * dv <= emitter.radius_m**2)
            value = np.where(
                on[:, None],
                (emitter.radiance(t.theta, t.phi) * t.cos4)[:, None]
                * t.fresnel
                * np.asarray(emitter.spectrum)[None, :],
                0.0,
            )
            if np.any(self.environment > 0):
                value -= self._hidden_environment(plane, t, on)
            out.append(value.reshape(m, per_pixel, 3).mean(axis=1))
        return np.concatenate(out), pixel_index, npx * per_pixel

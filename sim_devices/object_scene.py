"""What the simulated camera sees of an object lit by the ground-truth light.

Written from the physics of ``docs/measurement.md`` ("Diffuse reflectance under near light") and independent of
:mod:`processing`. The object is the polyhedron its mesh file describes (read with trimesh,
placed in the rig frame: :class:`~sim_devices.objects.ObjectGeometry`), with flat face
normals oriented towards the side each camera ray comes from.

A pixel's electron rate is, as for the mirrored ball (:mod:`sim_devices.optics`, without
the mirror's Fresnel factor)::

    rate = k · ⟨ L_o · cos⁴β ⟩_pixel area × aperture

with ``k`` the camera's ``sensitivity_e_per_s`` and β the sensor-side ray's angle to the
optical axis, estimated with ``samples_per_pixel`` rays per pixel (stratified sub-pixel
positions paired at random with stratified aperture points). A ray that hits the object
at point r with normal n, from view direction v, brings back

    L_o = Σ_e f(ω_e, v) · E_e                                          (per channel)
    E_e = I_e(θ_e, φ_e) · s_e · max(0, n·ω_e) / d_e² · V_e

- f: the surface truth's BRDF at the hit's UV (barycentric interpolation of the face's
  vertex UVs): the Lambertian ``(1 − m)·ρ/π`` plus, where the finish is glossy, the GGX
  microfacet lobe of :mod:`sim_devices.brdf` (roughness, specular weight and index,
  metalness per region); or, for the older highlight tests, ``ρ/π`` plus an
  energy-normalised, channel-neutral Blinn–Phong lobe ``k_s·(m + 8)/(8π)·(n·h_e)^m``;
- each emitter e is taken as a point at its disc centre p_e on the light plane: at 30 cm a
  0.5 mm disc differs from a point by (r/d)² ≈ 3·10⁻⁶ in irradiance (larger discs are not
  integrated over: a truth such as ``lambertian-disc``, 1 m wide, is *not* meant for this
  scene);
- I_e the emitter's truth radiant intensity (:meth:`Emitter.intensity_w_sr`; for a
  Lambertian disc ``L·cosθ·πr²``) in the direction (θ_e, φ_e) from p_e to r in the light
  frame, 0 where r lies at z ≤ 0 of the light frame; s_e its spectrum (R, G, B);
- ω_e the unit vector from r to p_e, d_e the distance;
- V_e ∈ {0, 1}: the shadow ray from r (offset ``shadow_offset_m`` along n) to p_e does not
  meet the mesh.

Rays that miss the object see the uniform environment radiance (0 by default; away from
the object each pixel's chief ray stands for the whole pixel); with a non-zero environment
the object is also lit by it as by an unoccluded uniform sky (``L_o += ρ · L_env``,
self-occlusion and the specular share ignored: for calibration images only). Rays the
light's housing blocks bring back nothing (it can only matter when the light stands
between the camera and the object). Diffraction is then applied per channel as the Airy
optical transfer function of the aperture (:func:`sim_devices.optics.apply_diffraction`).

Ray casting uses Embree (embreex) when installed, on a float32 copy of the mesh centred on
its bounding box (1e-8 m precision at these sizes); hit points are rebuilt in float64
from the hit face and its barycentric coordinates, exactly on the face.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from numpy.typing import ArrayLike

from drivers.contracts.rig import Rig
from drivers.pose import Pose
from sim_devices.brdf import Finish, specular_lobe
from sim_devices.lights import TruthLight
from sim_devices.objects import ObjectError, ObjectGeometry, SurfaceTruth, load_surface
from sim_devices.optics import (
    CameraOptics,
    LightPlane,
    Rendering,
    RenderStats,
    apply_diffraction,
    environment_rgb,
    unit_disc_samples,
)

try:  # Embree through embreex (a dependency, which trimesh loads too); else trimesh's ray casting
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh
except ImportError:  # pragma: no cover - embreex is a dependency
    rtcore_scene = TriangleMesh = None

PLASTIC = 1.32471795724474602596  # the R2 sequence's constant (Roberts 2018)


# --- ray casting -----------------------------------------------------------------------------------
class RayCaster:
    """First hits and occlusion tests against one triangle mesh (rig frame, metres)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices = np.asarray(vertices, dtype=float)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.offset = 0.5 * (self.vertices.min(axis=0) + self.vertices.max(axis=0))
        if rtcore_scene is None:  # pragma: no cover - embreex is a dependency
            self._scene = None
            self._mesh = trimesh.Trimesh(self.vertices - self.offset, self.faces, process=False)
            self.backend = type(self._mesh.ray).__name__
            return
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self._scene,
            vertices=(self.vertices - self.offset).astype(np.float32),
            indices=self.faces.astype(np.int32),
        )
        self.backend = "embree"

    def _local(self, origins: ArrayLike) -> np.ndarray:
        origins = np.asarray(origins, dtype=float)
        out = np.empty(origins.shape, dtype=np.float32)
        np.subtract(origins, self.offset, out=out, casting="same_kind")
        return out

    def first_hit(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Face index (−1 for a miss) and barycentric coordinates (N, 3) of each ray's first hit."""
        n = len(origins)
        if self._scene is not None:
            out = self._scene.run(self._local(origins), np.asarray(directions, dtype=np.float32), output=1)
            face = np.asarray(out["primID"], dtype=np.int64)
            face[np.asarray(out["geomID"]) < 0] = -1
            u, v = np.asarray(out["u"], float), np.asarray(out["v"], float)
            bary = np.stack([1.0 - u - v, u, v], axis=-1)
            return face, bary
        face = np.full(n, -1, dtype=np.int64)
        bary = np.zeros((n, 3))
        tri, ray, loc = self._mesh.ray.intersects_id(
            self._local(origins).astype(float), directions, multiple_hits=False, return_locations=True
        )
        face[ray] = tri
        bary[ray] = trimesh.triangles.points_to_barycentric(self._mesh.triangles[tri], loc)
        return face, bary

    def occluded(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """True where the mesh meets the ray before ``distances`` (unit directions)."""
        if self._scene is not None:
            out = self._scene.run(
                self._local(origins),
                np.asarray(directions, dtype=np.float32),
                dists=np.asarray(distances, dtype=np.float32),
                query="OCCLUDED",
            )
            return np.asarray(out) != -1
        tri, ray, loc = self._mesh.ray.intersects_id(
            self._local(origins).astype(float), directions, multiple_hits=False, return_locations=True
        )
        blocked = np.zeros(len(origins), dtype=bool)
        t = np.einsum("ij,ij->i", loc - self._local(origins)[ray], np.asarray(directions)[ray])
        blocked[ray[t < np.asarray(distances)[ray]]] = True
        return blocked


# --- the renderer -----------------------------------------------------------------------------------
@dataclass
class ObjectRenderStats(RenderStats):
    pixels_on_object: int = 0  # pixels with at least one sample on the object
    shadow_rays: int = 0
    backend: str = ""


class ObjectSceneRenderer:
    """Render the rig's object as the camera sees it with the light at a given pose.

    Same interface as :class:`~sim_devices.optics.MirrorBallRenderer`: ``render(light_pose)``
    returns the expected electron rates, ``truth`` may be swapped (None: the light is off),
    ``set_environment`` sets the uniform surroundings.

    Parameters
    ----------
    rig : Rig
        Camera, light housing and ``rig.object`` (the mesh and its pose).
    truth : TruthLight or None
        The emitters on the light plane.
    surface : SurfaceTruth, optional
        The object's reflectance (default: ``rig.simulation.surface``).
    samples_per_pixel : int
        Rays per pixel over the pixel's area × the aperture.
    diffraction : bool
        Apply the Airy pattern of each channel's wavelength.
    seed : int
        Seed of the sample positions.
    environment_radiance : float or (R, G, B)
        Uniform radiance of the surroundings (0: a dark room).
    shadow_offset_m : float
        Shadow rays start this far off the surface along the normal.
    chunk_rays : int
        Camera rays per batch (memory).
    """

    def __init__(
        self,
        rig: Rig,
        truth: TruthLight | None,
        *,
        surface: SurfaceTruth | str | None = None,
        samples_per_pixel: int = 4,
        diffraction: bool = True,
        seed: int = 0,
        environment_radiance: float | tuple[float, float, float] = 0.0,
        shadow_offset_m: float = 5e-6,
        chunk_rays: int = 400_000,
    ):
        if rig.object is None:
            raise ObjectError(f"{rig.name}: the rig has no [object] to render")
        if samples_per_pixel < 1:
            raise ValueError(f"samples_per_pixel must be >= 1, got {samples_per_pixel!r}")
        self.rig = rig
        self.truth = truth
        if surface is None or isinstance(surface, str):
            surface = load_surface(surface or rig.simulation.surface)
        self.surface = surface
        self.geometry = ObjectGeometry.from_rig(rig)
        if self.surface.varies and self.geometry.uv is None:
            raise ObjectError(
                f"{self.geometry.path}: the mesh has no texture coordinates, but surface "
                f"{self.surface.name!r} paints patches or maps in UV space"
            )
        self.caster = RayCaster(self.geometry.vertices, self.geometry.faces)
        self.camera = CameraOptics.from_rig(rig)
        self.samples_per_pixel = int(samples_per_pixel)
        self.diffraction = diffraction
        self.rng = np.random.default_rng(seed)
        self.shadow_offset = shadow_offset_m
        self.chunk_rays = chunk_rays
        self.sensitivity = rig.camera.sensitivity_e_per_s
        self.set_environment(environment_radiance)
        self._region: np.ndarray | None = None

    def set_environment(self, radiance: ArrayLike) -> None:
        """The uniform environment's radiance: a number, or one per channel (R, G, B)."""
        self.environment = environment_rgb(radiance)

    # --- which pixels can see the object ------------------------------------------------------
    def blur_radius_px(self) -> float:
        """Upper bound of a surface point's blur radius on the sensor (pixels)."""
        cam = self.camera
        depth = (self.geometry.vertices - cam.centre) @ cam.rotation[2]
        z_near, z_far = max(float(depth.min()), 1e-3), max(float(depth.max()), 1e-3)
        a, f = cam.aperture_radius, cam.sensor_distance
        if cam.focus_distance is None:
            blur = a * (1.0 + f / z_near)
        else:
            blur = a * f * max(abs(1.0 / z - 1.0 / cam.focus_distance) for z in (z_near, z_far))
        return blur / cam.pitch

    def object_pixels(self) -> np.ndarray:
        """Flat indices of the pixels some of whose rays may meet the object.

        Chief rays (pixel centre, aperture centre) over the object's projected bounding
        box, dilated by the largest blur radius plus two pixels.
        """
        if self._region is not None:
            return self._region
        cam = self.camera
        rel = (self.geometry.vertices - cam.centre) @ cam.rotation.T  # camera frame
        if np.any(rel[:, 2] <= 1e-6):  # the object reaches behind the camera: every pixel
            r0, r1, c0, c1 = 0, cam.height, 0, cam.width
        else:
            fpx = cam.sensor_distance / cam.pitch
            cols = cam.cx + fpx * rel[:, 0] / rel[:, 2]
            rows = cam.cy + fpx * rel[:, 1] / rel[:, 2]
            margin = self.blur_radius_px() + 2.0
            c0, c1 = (
                max(0, int(math.floor(cols.min() - margin))),
                min(cam.width, int(math.ceil(cols.max() + margin)) + 1),
            )
            r0, r1 = (
                max(0, int(math.floor(rows.min() - margin))),
                min(cam.height, int(math.ceil(rows.max() + margin)) + 1),
            )
        if c0 >= c1 or r0 >= r1:
            self._region = np.zeros(0, dtype=np.int64)
            return self._region
        rr, cc = np.mgrid[r0:r1, c0:c1]
        zero = np.zeros(cc.size)
        (ox, oy, oz), (dx, dy, dz), _ = cam.rays(cc.ravel().astype(float), rr.ravel().astype(float), zero, zero)
        face, _ = self.caster.first_hit(np.column_stack([ox, oy, oz]), np.column_stack([dx, dy, dz]))
        hit = (face >= 0).reshape(rr.shape).astype(np.uint8)
        margin = int(math.ceil(self.blur_radius_px() + 2.0))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
        near = cv2.dilate(hit, kernel).astype(bool)
        self._region = (rr * cam.width + cc)[near].astype(np.int64)
        return self._region

    # --- rendering -------------------------------------------------------------------------------
    def render(self, light_pose: Pose) -> Rendering:
        """Expected electron rates (3, H, W) with the light at ``light_pose`` (rig frame)."""
        cam = self.camera
        stats = ObjectRenderStats(backend=self.caster.backend)
        plane = LightPlane.at(self.rig, light_pose)
        rate = np.zeros((3, cam.height * cam.width))
        region = self.object_pixels()
        if np.any(self.environment > 0):  # the background, by each pixel's chief ray
            rows, cols = np.divmod(np.arange(cam.height * cam.width), cam.width)
            zero = np.zeros(cols.size)
            (ox, oy, oz), (dx, dy, dz), cos4 = cam.rays(cols.astype(float), rows.astype(float), zero, zero)
            if plane.housing_radius > 0 and self._housing_in_view(plane):
                far = 10.0  # metres: beyond the rig
                cos4 = np.where(
                    plane.blocks_segment((ox, oy, oz), (ox + far * dx, oy + far * dy, oz + far * dz)), 0.0, cos4
                )
            rate += self.environment[:, None] * cos4[None, :]
        spp = self.samples_per_pixel
        step = max(1, self.chunk_rays // spp)
        hit_pixels = 0
        for s in range(0, region.size, step):
            pix = region[s : s + step]
            value, hits, rays, shadow = self._render_pixels(plane, pix)
            rate[:, pix] = value.T
            hit_pixels += hits
            stats.rays_traced += rays
            stats.shadow_rays += shadow
        stats.pixels_on_object = hit_pixels
        stats.pixels_on_ball = hit_pixels
        rate = rate.reshape(3, cam.height, cam.width) * self.sensitivity
        if self.diffraction:
            for ch in range(3):
                rate[ch] = apply_diffraction(
                    rate[ch], cam.pitch, 2 * cam.aperture_radius, cam.sensor_distance, cam.wavelengths[ch]
                )
            np.clip(rate, 0.0, None, out=rate)
        return Rendering(rate, stats)

    def sample_rays(self, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``samples_per_pixel`` rays per pixel: sensor points (col, row) and aperture points.

        Sub-pixel positions follow the R2 sequence, randomly shifted per pixel; aperture
        points a randomly shifted and rotated sunflower spiral per pixel; the two are paired
        in a random order per pixel.
        """
        cam, spp, m = self.camera, self.samples_per_pixel, pix.size
        rows, cols = np.divmod(pix, cam.width)
        j = np.arange(spp)[None, :]
        shift = self.rng.random((m, 1, 2))
        sub = np.stack([j / PLASTIC, j / PLASTIC**2], axis=-1) + shift  # (m, spp, 2)
        sub = sub - np.floor(sub) - 0.5
        disc = cam.aperture_radius * unit_disc_samples(spp, (m,), self.rng)  # (m, spp, 2)
        order = self.rng.permuted(np.broadcast_to(np.arange(spp), (m, spp)), axis=1)
        disc = np.take_along_axis(disc, order[..., None], axis=1)
        sc = (cols[:, None] + sub[..., 0]).ravel()
        sr = (rows[:, None] + sub[..., 1]).ravel()
        return sc, sr, disc[..., 0].ravel(), disc[..., 1].ravel()

    def _render_pixels(self, plane: LightPlane, pix: np.ndarray) -> tuple[np.ndarray, int, int, int]:
        """Mean ``L_o · cos⁴β`` (unscaled) per pixel (m, 3); pixels with hits; rays cast."""
        cam, spp = self.camera, self.samples_per_pixel
        sc, sr, ax, ay = self.sample_rays(pix)
        (ox, oy, oz), (dx, dy, dz), cos4 = cam.rays(sc, sr, ax, ay)
        origins = np.column_stack([ox, oy, oz])
        dirs = np.column_stack([dx, dy, dz])
        face, bary = self.caster.first_hit(origins, dirs)
        hit = face >= 0
        radiance = np.zeros((sc.size, 3))
        radiance[~hit] = self.environment
        idx = np.flatnonzero(hit)
        shadow_rays = 0
        if idx.size:
            f = face[idx]
            points = np.einsum("nk,nkj->nj", bary[idx], self.geometry.triangles[f])
            normals = self.geometry.normals[f]
            view = -dirs[idx]
            flip = np.einsum("ij,ij->i", normals, view) < 0.0
            normals[flip] *= -1.0
            uv = self.geometry.uv_at(f, bary[idx]) if self.surface.varies else None
            albedo = self.surface.albedo_at(uv, idx.size)
            finish = self.surface.finish_at(uv, idx.size) if self.surface.glossy else None
            value, shadow_rays = self.shade(plane, points, normals, view, albedo, finish)
            radiance[idx] = value + albedo * self.environment[None, :]
        if plane.housing_radius > 0 and self._housing_in_view(plane):
            far = np.where(hit[:, None], 0.0, 10.0)  # misses: 10 m on
            ends = np.where(
                hit[:, None],
                np.einsum("nk,nkj->nj", bary, self.geometry.triangles[np.maximum(face, 0)]),
                origins + far * dirs,
            )
            blocked = plane.blocks_segment((ox, oy, oz), (ends[:, 0], ends[:, 1], ends[:, 2]))
            radiance[blocked] = 0.0
        value = (radiance * cos4[:, None]).reshape(pix.size, spp, 3).mean(axis=1)
        hits = int(np.count_nonzero(hit.reshape(pix.size, spp).any(axis=1)))
        return value, hits, sc.size, shadow_rays

    def _housing_in_view(self, plane: LightPlane) -> bool:
        """False when the housing lies wholly behind the camera (it cannot block a ray)."""
        cam = self.camera
        half = 0.5 * plane.housing_depth
        centre = plane.origin - half * plane.rotation[:, 2]
        reach = math.hypot(plane.housing_radius, half)
        return float(cam.rotation[2] @ (centre - cam.centre)) + reach > 0.0

    def shadowed(self, points: np.ndarray, normals: np.ndarray, target: np.ndarray) -> np.ndarray:
        """True where the mesh stands between each point (started just off the surface,
        along its normal) and the target point."""
        start = points + self.shadow_offset * normals
        towards = target - start
        reach = np.sqrt(np.einsum("ij,ij->i", towards, towards))
        return self.caster.occluded(start, towards / reach[:, None], reach)

    def shade(
        self,
        plane: LightPlane,
        points: np.ndarray,
        normals: np.ndarray,
        view: np.ndarray,
        albedo: np.ndarray,
        finish: Finish | None = None,
    ) -> tuple[np.ndarray, int]:
        """Outgoing radiance (N, 3) at surface points lit by the truth's emitters.

        ``normals`` must face the viewer (unit ``view`` directions point from the surface
        towards the camera); ``finish`` (None: matte) adds the microfacet lobe and dims the
        diffuse part by ``1 − metalness``. Returns the radiance and the number of shadow
        rays cast.
        """
        n_pts = len(points)
        if self.truth is None or n_pts == 0:
            return np.zeros((n_pts, 3)), 0
        spec = self.surface.specular
        glossy = spec is not None and spec.k_s > 0
        diffuse_e = np.zeros((n_pts, 3))
        specular_e = np.zeros((n_pts, 3)) if glossy else None
        lobed = np.flatnonzero(finish.glossy) if finish is not None else np.zeros(0, np.int64)
        lobe_e = np.zeros((n_pts, 3)) if lobed.size else None
        in_lobe = np.full(n_pts, -1, np.int64)
        in_lobe[lobed] = np.arange(lobed.size)
        rot, origin = plane.rotation, plane.origin
        px, py, pz = (np.ascontiguousarray(points[:, i]) for i in range(3))
        nx, ny, nz = (np.ascontiguousarray(normals[:, i]) for i in range(3))
        local = (points - origin) @ rot  # light frame: x_local = Rᵀ (x − o)
        lz = np.ascontiguousarray(local[:, 2])
        shadow_rays = 0
        for emitter in self.truth.emitters:
            u, v = emitter.centre_m
            ex, ey, ez = origin + rot[:, 0] * u + rot[:, 1] * v  # p_e in the rig frame
            wx, wy, wz = ex - px, ey - py, ez - pz
            inv_d = 1.0 / np.sqrt(wx * wx + wy * wy + wz * wz)
            cos_n = (nx * wx + ny * wy + nz * wz) * inv_d
            sel = np.flatnonzero((cos_n > 0.0) & (lz > 0.0))
            if sel.size == 0:
                continue
            inv = inv_d[sel]
            theta = np.arccos(np.clip(lz[sel] * inv, -1.0, 1.0))
            phi = np.arctan2(local[sel, 1] - v, local[sel, 0] - u)
            intensity = np.asarray(emitter.intensity_w_sr(theta, phi), dtype=float)
            keep = intensity > 0.0
            if not keep.all():
                sel, inv, intensity = sel[keep], inv[keep], intensity[keep]
            if sel.size == 0:
                continue
            blocked = self.shadowed(points[sel], normals[sel], np.array([ex, ey, ez]))
            shadow_rays += sel.size
            if blocked.any():
                free = ~blocked
                sel, inv, intensity = sel[free], inv[free], intensity[free]
            irradiance = intensity * cos_n[sel] * inv * inv
            e = irradiance[:, None] * np.asarray(emitter.spectrum, dtype=float)[None, :]
            diffuse_e[sel] += e
            if glossy:
                assert spec is not None and specular_e is not None  # glossy: both there
                hx = wx[sel] * inv + view[sel, 0]
                hy = wy[sel] * inv + view[sel, 1]
                hz = wz[sel] * inv + view[sel, 2]
                nh = (nx[sel] * hx + ny[sel] * hy + nz[sel] * hz) / np.sqrt(hx * hx + hy * hy + hz * hz)
                lobe = spec.k_s * (spec.exponent + 8.0) / (8.0 * math.pi) * np.clip(nh, 0.0, None) ** spec.exponent
                specular_e[sel] += lobe[:, None] * e
            if lobe_e is not None and finish is not None:
                at = sel[in_lobe[sel] >= 0]
                towards_light = np.column_stack([wx[at], wy[at], wz[at]]) * inv_d[at, None]
                f_spec = specular_lobe(towards_light, view[at], normals[at], albedo[at], finish.take(in_lobe[at]))
                lobe_e[at] += f_spec * e[np.searchsorted(sel, at)]
        diffuse = albedo if finish is None else albedo * (1.0 - finish.metalness)[:, None]
        out = diffuse * (1.0 / math.pi) * diffuse_e
        if specular_e is not None:  # glossy
            out += specular_e
        if lobe_e is not None:
            out += lobe_e
        return out, shadow_rays

"""Templates: the image one source alone makes at one position, per unit radiant intensity."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from drivers.pose import Pose
from processing.trace import RigGeometry, conductor_reflectance, housing_blocks, specular_points
from processing.unmixing.fresnel import FresnelPupil, fresnel_kernel, rounded_curvature, shadow_curvature
from processing.unmixing.kernels import PointSpreadCorrection
from processing.unmixing.measured import MeasuredKernels
from processing.unmixing.psf import convex_coverage, convolve_full_each, convolve_same, diffract, polygon_area
from processing.unmixing.sources import Source


@dataclass
class Template:
    """One source's image at one position, per unit radiant intensity (1 W/sr).

    ``image`` is (3, h, w): the electron rate per second each channel's pixels would see
    in the patch whose top-left pixel is (row0, col0).
    """

    source: str
    row0: int
    col0: int
    image: np.ndarray
    theta: float
    phi: float
    alpha: float
    fresnel: np.ndarray
    solid_angle: float
    image_centre: tuple[float, float]  # chief ray's pixel (col, row)
    blur_radius_px: float


@dataclass
class TemplateBuilder:
    """Templates of sources on the light plane for a rig (``docs/measurement.md``, estimator 3).

    The camera's blur is the aperture's geometric shadow (traced through the mirror) convolved
    with each channel's Airy pattern; with ``pupil``, the Fresnel pattern of that aperture
    over each channel's band instead (:mod:`processing.unmixing.fresnel`), its curvature read
    off the same traced shadow; with ``measured``, the lab's measured point spread
    (:mod:`processing.unmixing.measured`). ``airy_margin_px`` is how far the diffraction
    reaches beyond the geometric image, in pixels. ``correction``, the point spread refined
    from the sweep (:mod:`processing.unmixing.point_spread_fit`), is added to either kernel
    within its reach.
    """

    geometry: RigGeometry
    sensitivity: float
    diffraction: bool = True
    rim_points: int = 96
    oversample: int = 4
    airy_margin_px: int = 32
    pupil: FresnelPupil | None = None
    measured: MeasuredKernels | None = None
    correction: PointSpreadCorrection | None = None

    def build(self, source: Source, light_pose: Pose) -> Template | None:
        """The source's template, or None if the ball does not show it to the camera."""
        g = self.geometry
        rot, origin = light_pose.rotation, light_pose.position
        q = origin + rot @ np.array([source.centre[0], source.centre[1], 0.0])
        pinhole = g.camera_centre
        # Every specular path of the template in one batch: the chief path (source centre
        # to pinhole), the pinhole's rim, and the source disc's outline.
        angles = np.linspace(0.0, 2.0 * math.pi, self.rim_points, endpoint=False)
        rim_cam = np.stack(
            [g.aperture_radius * np.cos(angles), g.aperture_radius * np.sin(angles), np.zeros_like(angles)], -1
        )
        rim = pinhole + rim_cam @ g.R  # camera -> rig
        disc_angles = np.linspace(0.0, 2.0 * math.pi, 24, endpoint=False)
        disc = origin + (
            np.stack(
                [
                    source.centre[0] + source.radius * np.cos(disc_angles),
                    source.centre[1] + source.radius * np.sin(disc_angles),
                    np.zeros_like(disc_angles),
                ],
                -1,
            )
            @ rot.T
        )
        m = self.rim_points
        starts = np.concatenate([q[None, :], np.broadcast_to(q, rim.shape), disc])
        ends = np.concatenate([pinhole[None, :], rim, np.broadcast_to(pinhole, disc.shape)])
        found = specular_points(starts, ends, g.ball_centre, g.ball_radius)
        p0, paths, disc_paths = found[0], found[1 : 1 + m], found[1 + m :]
        emit = (p0 - q) / np.linalg.norm(p0 - q)
        local = rot.T @ emit
        if local[2] <= 0.0:
            return None  # the ball is behind the light plane
        if housing_blocks(pinhole[None, :], p0[None, :], light_pose, g.housing_radius, g.housing_depth)[0]:
            return None
        normal = (p0 - g.ball_centre) / g.ball_radius
        cos_alpha = float(np.dot(normal, (q - p0) / np.linalg.norm(q - p0)))
        fresnel = conductor_reflectance(np.array([cos_alpha]), g.n, g.k)[0]
        # Where the rim's specular paths land on the sensor.
        outline = self._sensor_points(paths, rim_cam)
        # The solid angle of those paths at the source (a small polygon of directions).
        directions = (paths - q) / np.linalg.norm(paths - q, axis=-1, keepdims=True)
        axis = directions.mean(axis=0)
        axis /= np.linalg.norm(axis)
        e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        tangent = np.stack([directions @ e1, directions @ e2], -1) / (directions @ axis)[:, None]
        solid_angle = polygon_area(tangent)
        # The source disc's own image through the pinhole's centre.
        disc_image = g.project(disc_paths)
        centre_px = g.project(p0[None, :])[0]
        top, left, pixels, area_ratio = self._blurred(outline, rim_cam, disc_image - centre_px, centre_px)
        scale = self.sensitivity * g.sensor_distance**2 / (g.pitch**2 * math.pi * g.aperture_radius**2)
        scale *= solid_angle * area_ratio
        pixels = pixels * (scale * fresnel)[:, None, None]
        theta = float(math.acos(np.clip(local[2], -1.0, 1.0)))
        phi = float(math.atan2(local[1], local[0]))
        blur = float(np.sqrt(polygon_area(outline) / math.pi))
        return Template(
            source.name,
            top,
            left,
            pixels,
            theta,
            phi,
            float(math.acos(min(1.0, cos_alpha))),
            fresnel,
            solid_angle,
            (float(centre_px[0]), float(centre_px[1])),
            blur,
        )

    def _sensor_points(self, paths: np.ndarray, rim_cam: np.ndarray) -> np.ndarray:
        """Where the rays from reflection points through rim points land, in pixels.

        A thin lens of focal length F images an object point P (distance u) at
        P' = -P v/u, v = 1/(1/F - 1/u); the ray through the rim point a heads for P' and
        meets the sensor at a + (P' - a) f / v. With 1/F = 0 this is the pinhole's
        straight line.
        """
        g = self.geometry
        p_cam = paths @ g.R.T + g.t
        u = p_cam[:, 2]
        v = 1.0 / (g.inverse_focal - 1.0 / u)
        image = np.stack([-p_cam[:, 0] * v / u, -p_cam[:, 1] * v / u, -v], axis=-1)
        sensor = rim_cam + (image - rim_cam) * (g.sensor_distance / v)[:, None]  # on the plane z = -f
        return np.stack([g.K[0, 2] - sensor[:, 0] / g.pitch, g.K[1, 2] - sensor[:, 1] / g.pitch], -1)

    def _blurred(
        self, outline: np.ndarray, rim_cam: np.ndarray, disc: np.ndarray, centre: np.ndarray
    ) -> tuple[int, int, np.ndarray, float]:
        """The source's image blurred as the builder models the camera: (top, left, pixels, the
        aperture's area over the round rim's, whose solid angle scales the template)."""
        g = self.geometry
        reach = int(math.ceil(float(np.max(np.linalg.norm(outline - centre, axis=1))))) + self.airy_margin_px
        if self.measured is not None:
            measured = self.measured
            kernels = [measured.kernel(c, reach) for c in range(3)]
            return (*self._convolved(self._corrected(kernels), disc, centre), 1.0)
        if self.pupil is None:
            return (*self._render(outline, disc, centre), 1.0)
        # The kernels are not renormalised: a hard edge's far tails (a few per cent of the light
        # beyond the reach) land outside the template, as in the frames.
        curvature = rounded_curvature(shadow_curvature(rim_cam[:, :2], outline, g.pitch, g.sensor_distance))
        shape = self.pupil.shape(g.aperture_radius, g.aperture_shape)
        kernels = [
            fresnel_kernel(shape, curvature, float(g.sensor_distance), float(g.pitch), self.pupil.bands[c], reach)
            for c in range(3)
        ]
        xx, xy, yy = g.aperture_shape  # the aperture's area over the round rim's
        return (*self._convolved(self._corrected(kernels), disc, centre), xx * yy - xy * xy)

    def _corrected(self, kernels: list[np.ndarray]) -> list[np.ndarray]:
        return kernels if self.correction is None else self.correction.added_to(kernels)

    def _convolved(
        self, kernels: list[np.ndarray], disc: np.ndarray, centre: np.ndarray
    ) -> tuple[int, int, np.ndarray]:
        """The disc's sharp image about ``centre`` (pixel-integrated on the fine grid), convolved
        with each channel's point spread (``kernels``, square, the chief ray's pixel in the
        middle): the Fresnel pattern of the wave's curvature, or the measured one."""
        os_ = self.oversample
        half = int(math.ceil(float(np.max(np.linalg.norm(disc, axis=1))) + 2.0))
        c0, r0 = int(round(centre[0])) - half, int(round(centre[1])) - half
        n = 2 * half + 1
        sub = 1.0 / os_
        xs = c0 - 0.5 + (np.arange(n * os_) + 0.5) * sub - centre[0]
        ys = r0 - 0.5 + (np.arange(n * os_) + 0.5) * sub - centre[1]
        if polygon_area(disc) > (0.25 * sub) ** 2:
            sharp = convex_coverage(disc, xs, ys, sub)
        else:  # a point: its weight shared bilinearly between the four nearest fine samples
            sharp = np.outer(np.clip(1.0 - np.abs(ys) / sub, 0.0, None), np.clip(1.0 - np.abs(xs) / sub, 0.0, None))
        sharp /= sharp.sum()
        geometric = sharp.reshape(n, os_, n, os_).sum(axis=(1, 3))
        reach = kernels[0].shape[0] // 2
        channels = convolve_full_each(geometric, kernels)
        return r0 - reach, c0 - reach, channels

    def _render(self, outline: np.ndarray, disc: np.ndarray, centre: np.ndarray) -> tuple[int, int, np.ndarray]:
        g, os_ = self.geometry, self.oversample
        reach = float(np.max(np.linalg.norm(outline - centre, axis=1)) + np.max(np.linalg.norm(disc, axis=1)) + 2.0)
        half = int(math.ceil(reach))
        c0, r0 = int(round(centre[0])) - half, int(round(centre[1])) - half
        n = 2 * half + 1
        sub = 1.0 / os_
        xs = c0 - 0.5 + (np.arange(n * os_) + 0.5) * sub
        ys = r0 - 0.5 + (np.arange(n * os_) + 0.5) * sub
        blur = convex_coverage(outline, xs, ys, sub)
        blur /= blur.sum()
        # The source's disc image, centred, as a kernel on the same fine grid.
        k_half = int(math.ceil(np.max(np.abs(disc)) * os_)) + 2
        kx = (np.arange(-k_half, k_half + 1)) * sub
        kernel = convex_coverage(disc, kx, kx, sub) if polygon_area(disc) > (0.25 * sub) ** 2 else None
        if kernel is not None and kernel.sum() > 0:
            blur = convolve_same(blur, kernel / kernel.sum())
        geometric = blur.reshape(n, os_, n, os_).sum(axis=(1, 3))
        margin = self.airy_margin_px if self.diffraction else 0
        size = n + 2 * margin
        if self.diffraction:
            padded = sfft.next_fast_len(4 * size, real=True)
            channels = diffract(
                geometric,
                size,
                margin,
                padded,
                float(g.pitch),
                float(2 * g.aperture_radius),
                float(g.sensor_distance),
                [float(g.wavelengths[c]) for c in range(3)],
            )
        else:
            channels = np.zeros((3, size, size))
            channels[:, margin : margin + n, margin : margin + n] = geometric
        return r0 - margin, c0 - margin, channels

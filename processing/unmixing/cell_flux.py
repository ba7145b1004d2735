"""The fast path: flux-conserving chief-ray cell sums (``docs/measurement.md``, estimator 4)."""

from __future__ import annotations

import math

import numpy as np

from drivers.pose import Pose
from processing.hdr.mosaic import cfa_channels
from processing.radiometry import ElectronRates
from processing.trace import ChiefRays, RigGeometry, footprint_areas, specular_points, trace_pixels
from processing.unmixing.sources import Source


def cell_sums(
    rate_e: np.ndarray | ElectronRates,
    usable: np.ndarray,
    geometry: RigGeometry,
    sensitivity: float,
    sources: list[Source],
    light_pose: Pose,
    cell_radius: float,
    cfa_pattern: str = "RGGB",
) -> np.ndarray:
    """``I_c ≈ Σ L_i A_i cos θ_i`` over the pixels whose chief ray lands within ``cell_radius``
    of each source (``docs/measurement.md``, estimator 4), per channel: (n_sources, 3).

    Only the lit pixels in :func:`cell_pixel_boxes` are traced (a few hundred, where every
    lit pixel of the frame is ~10⁵ and 35 ms a position): a superset of those
    whose chief ray can land in a cell, so the same pixels pass the exact test below, in
    the same (row-major) order. The trace is per pixel, so each pixel's numbers do not
    depend on which others are traced with it, and the sums are those of tracing every
    lit pixel (to the bit on the benchmark run's 66 positions). Without such boxes every
    lit pixel is traced.
    """
    boxes = cell_pixel_boxes(geometry, light_pose, sources, cell_radius, rate_e.shape)
    if boxes is None:
        rows, cols = np.nonzero(usable & (rate_e[:, :] > 0))  # [:, :]: an array, or a lazy view of one
    else:
        width = rate_e.shape[1]
        flat = [(np.arange(r0, r1)[:, None] * width + np.arange(c0, c1)[None, :]).ravel() for r0, r1, c0, c1 in boxes]
        rows, cols = np.divmod(np.unique(np.concatenate(flat)) if flat else np.zeros(0, np.intp), width)
        lit = usable[rows, cols] & (rate_e[rows, cols] > 0)
        rows, cols = rows[lit], cols[lit]
    if rows.size == 0:
        return np.zeros((len(sources), 3))
    rays = trace_pixels(geometry, light_pose, cols.astype(float), rows.astype(float))
    out = np.zeros((len(sources), 3))
    near = np.zeros(rays.valid.shape, bool)
    for s in sources:
        near |= np.hypot(rays.u - s.centre[0], rays.v - s.centre[1]) <= cell_radius
    keep = rays.valid & near
    if not np.any(keep):
        return out
    # The kept pixels' rays: the trace is per pixel, so a subset of it is their trace.
    sub_rays = ChiefRays(
        **{
            name: value[keep] if isinstance(value, np.ndarray) and value.shape[:1] == keep.shape else value
            for name, value in vars(rays).items()
        }
    )
    area = footprint_areas(geometry, light_pose, sub_rays)
    channel = cfa_channels(cfa_pattern, rows[keep], cols[keep])
    for i, s in enumerate(sources):
        inside = np.hypot(sub_rays.u - s.centre[0], sub_rays.v - s.centre[1]) <= cell_radius
        inside &= np.isfinite(area)
        for c in range(3):
            sel = inside & (channel == c)
            radiance = rate_e[rows[keep][sel], cols[keep][sel]] / (
                sensitivity * sub_rays.fresnel[sel, c] * sub_rays.cos4[sel]
            )
            # Each channel samples only its own photosites: scale by the share of the CFA.
            share = {0: 4.0, 1: 2.0, 2: 4.0}[c]
            out[i, c] = share * np.sum(radiance * area[sel] * np.cos(sub_rays.theta[sel]))
    return out


def cell_pixel_boxes(
    geometry: RigGeometry,
    light_pose: Pose,
    sources: list[Source],
    cell_radius: float,
    shape: tuple[int, int],
    margin_px: float = 1.0,
) -> list[tuple[int, int, int, int]] | None:
    """Per source, a box of pixels ``(row0, row1, col0, col1)`` (ends excluded, within
    ``shape``) holding every pixel whose chief ray lands within ``cell_radius`` of it;
    None when such boxes cannot be vouched for (then every pixel is a candidate).

    Why the boxes hold every such pixel: the chief-ray map from pixels to the light plane
    is continuous and one-to-one where rays reach the plane (a point of the plane has one
    specular point on a convex ball that both it and the pinhole see), so the pixels of
    a cell are those inside the image of the cell's circle, and a box holding that closed
    curve holds them. The curve is found backwards, by exact specular paths from points
    of the circle to the pinhole, and each point is checked forwards: the chief ray of the
    pixel found must land back on the circle point (to 1e-6 of the radius: the iteration
    converged). The points are spaced at most ``gap`` ≤ 0.5 px apart along the curve,
    and an arc that short on a smooth curve stays within ``gap`` of its ends, so the
    points' bounding box grown by ``gap + margin_px`` holds the whole curve with room
    to spare; its rows and columns are then rounded outwards to whole pixels (centres at
    integers, as :func:`processing.trace.trace_pixels` takes them).

    None when the ball is not wholly in front of the light plane (the map is not one-to-one
    there) and of the camera, when a circle point does not check out, or when the boxes
    are so large that tracing every pixel is as cheap.
    """
    height, width = shape
    rot, origin = light_pose.rotation, light_pose.position
    g = geometry
    in_front_of_light = float((g.ball_centre - origin) @ rot[:, 2]) > g.ball_radius
    in_front_of_camera = float((g.R @ (g.ball_centre - g.camera_centre))[2]) > g.ball_radius  # projections hold
    if not (in_front_of_light and in_front_of_camera and sources and 0.0 <= cell_radius < math.inf):
        return None
    centres = np.array([s.centre for s in sources], float)  # (S, 2)
    count = 64
    while True:
        angles = np.linspace(0.0, 2.0 * math.pi, count, endpoint=False)
        circle = centres[:, None, :] + cell_radius * np.stack([np.cos(angles), np.sin(angles)], -1)[None]  # (S, n, 2)
        local = np.concatenate([circle, np.zeros(circle.shape[:2] + (1,))], axis=-1)
        points = origin + local @ rot.T
        found = specular_points(points, g.camera_centre, g.ball_centre, g.ball_radius)
        pixels = g.project(found.reshape(-1, 3)).reshape(len(sources), count, 2)
        if not np.all(np.isfinite(pixels)):
            return None
        gap = float(np.max(np.linalg.norm(pixels - np.roll(pixels, 1, axis=1), axis=-1)))
        if gap <= 0.5:
            break
        if count >= 8192:
            return None  # a cell spanning thousands of pixels: trace them all
        count = min(8192, int(math.ceil(count * gap / 0.4)))
    rays = trace_pixels(g, light_pose, pixels[..., 0].ravel(), pixels[..., 1].ravel())
    miss = np.hypot(rays.u - circle[..., 0].ravel(), rays.v - circle[..., 1].ravel())
    if not (np.all(rays.reaches_plane) and np.all(miss <= 1e-6 * cell_radius)):
        return None
    grow = gap + margin_px
    boxes, total = [], 0
    for p in pixels:
        r0 = max(0, int(math.floor(p[:, 1].min() - grow)))
        r1 = min(height, int(math.ceil(p[:, 1].max() + grow)) + 1)
        c0 = max(0, int(math.floor(p[:, 0].min() - grow)))
        c1 = min(width, int(math.ceil(p[:, 0].max() + grow)) + 1)
        if r1 > r0 and c1 > c0:
            boxes.append((r0, r1, c0, c1))
            total += (r1 - r0) * (c1 - c0)
    return boxes if total <= height * width // 8 else None

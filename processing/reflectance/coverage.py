"""Which parts of an object a schedule will show a highlight on, worked out before the run.

A glossy surface's lobe can only be measured at a point whose mirror direction some light
position comes near: the half vector ``h`` between the direction to the light and the
direction to the camera must lie within the lobe's width of the normal ``n``. For a GGX
lobe of roughness α the distribution, relative to its peak, is

    D(h)/D(n) = α⁴ / ((n·h)²(α² − 1) + 1)²

(Walter et al., EGSR 2007), so a light position gives a *highlight sample* at a point when
that ratio reaches ``lobe_fraction`` there, the point faces the light, no part of the mesh
stands between them, and the camera sees the point (its chief ray, on the superpixel grid
the reflectance step uses). The light is taken as a point at its plane's origin: the
coverage is a plan, not a measurement. Counting these samples per point, over the camera's
view and in the mesh's UV layout, tells a technician before an hour of captures which
texels will have their roughness pinned down by the data and which will have to borrow it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from drivers.contracts.rig import Rig
from drivers.pose import Pose
from processing.reflectance.codes import PIXEL_VALID, ReflectanceError, ReflectanceSettings
from processing.reflectance.estimate import uv_at_points
from processing.reflectance.maps import splat_uv
from processing.reflectance.run import load_mesh
from processing.reflectance.samples import surface_seen


def ggx_relative_lobe(cos_h: np.ndarray, roughness: float) -> np.ndarray:
    """``D(h)/D(n)`` of a GGX lobe at ``cos_h = n·h`` (1 at the peak, 0 below the surface).

    >>> round(float(ggx_relative_lobe(np.array(1.0), 0.2)), 12)
    1.0
    """
    c = np.clip(np.asarray(cos_h, dtype=float), 0.0, 1.0)
    a2 = roughness * roughness
    return np.where(c > 0.0, a2 * a2 / (c * c * (a2 - 1.0) + 1.0) ** 2, 0.0)


@dataclass
class HighlightCoverage:
    """Highlight samples per point the camera sees, for one roughness.

    ``counts`` (H/2, W/2): the number of light positions giving a highlight sample at each
    superpixel's point, −1 where the pixel is background or not usable (edges, grazing
    views); ``texture`` the same counts in UV space (NaN where the camera sees nothing),
    None for a mesh without UVs.
    """

    roughness: float
    lobe_fraction: float
    positions: int
    counts: np.ndarray
    texture: np.ndarray | None

    def share(self, at_least: int = 1) -> float:
        """The share of the usable points with at least ``at_least`` highlight samples."""
        usable = self.counts >= 0
        return float(np.mean(self.counts[usable] >= at_least)) if usable.any() else 0.0

    def summary(self) -> dict[str, Any]:
        usable = self.counts >= 0
        values = self.counts[usable]
        return {
            "roughness": self.roughness,
            "lobe_fraction": self.lobe_fraction,
            "positions": self.positions,
            "points": int(values.size),
            "share_with_highlight": self.share(1),
            "share_with_three": self.share(3),
            "median_highlights": float(np.median(values)) if values.size else 0.0,
        }


def highlight_coverage(
    rig: Rig,
    *,
    roughness: float = 0.2,
    lobe_fraction: float = 0.25,
    light_poses: Sequence[Pose] | None = None,
    texture_size: int = 256,
    settings: ReflectanceSettings | None = None,
) -> HighlightCoverage:
    """Count each visible point's highlight samples under a schedule (the rig's by default).

    Parameters
    ----------
    rig : Rig
        With an ``[object]``: the mesh, its pose and the camera that sees it.
    roughness : float
        The GGX α the plan is made for (the roughest lobe to be measured is the easiest to
        hit; the smoothest the hardest).
    lobe_fraction : float
        How far down its peak the lobe must still be for a sample to count, in (0, 1].
    light_poses : sequence of Pose, optional
        The light's poses (default: the rig's schedule).
    texture_size : int
        Texels along a side of the UV map.

    Raises
    ------
    ReflectanceError
        The rig has no object, or a parameter is out of its range (one line each).
    """
    if rig.object is None:
        raise ReflectanceError(f"{rig.name}: the rig has no [object] to plan a coverage for")
    if not 0.0 < roughness <= 1.0:
        raise ReflectanceError(f"roughness: {roughness:g} is not in (0, 1]")
    if not 0.0 < lobe_fraction <= 1.0:
        raise ReflectanceError(f"lobe_fraction: {lobe_fraction:g} is not in (0, 1]")
    settings = settings or ReflectanceSettings()
    poses = list(light_poses) if light_poses is not None else rig.light_poses()
    mesh = load_mesh(rig.object.mesh, rig.object.units_m, rig.object.pose.to_pose())
    shape = (rig.camera.height // 2, rig.camera.width // 2)
    surface = surface_seen(rig.camera, mesh, shape, settings, str(rig.object.mesh))
    usable = surface.reason[surface.rows, surface.cols] == PIXEL_VALID
    points, normals, view = surface.points[usable], surface.normals[usable], surface.view[usable]
    counts_at = np.zeros(len(points), np.int64)
    offset = 1e-6 * float(np.linalg.norm(mesh.extents))
    for pose in poses:
        towards = pose.position - points
        distance = np.linalg.norm(towards, axis=1)
        omega = towards / distance[:, None]
        half = omega + view
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        cos_h = np.einsum("ij,ij->i", normals, half)
        lit = np.einsum("ij,ij->i", normals, omega) > 0.0
        candidate = np.flatnonzero(lit & (ggx_relative_lobe(cos_h, roughness) >= lobe_fraction))
        if candidate.size:
            start = points[candidate] + offset * normals[candidate]
            blocked = mesh.ray.intersects_any(start, omega[candidate])
            counts_at[candidate[~blocked]] += 1
    counts = np.full(shape, -1, np.int64)
    counts[surface.rows[usable], surface.cols[usable]] = counts_at
    uv = uv_at_points(mesh, surface.faces[usable], points)
    texture = None if uv is None else splat_uv(uv, counts_at[:, None].astype(float), texture_size)[..., 0]
    return HighlightCoverage(roughness, lobe_fraction, len(poses), counts, texture)


def lobe_half_width_deg(roughness: float, lobe_fraction: float) -> float:
    """The angle between ``n`` and ``h`` at which the GGX lobe falls to ``lobe_fraction`` of its peak.

    >>> round(lobe_half_width_deg(0.15, 0.5), 1)
    5.6
    """
    a2 = roughness * roughness
    root = a2 / math.sqrt(lobe_fraction)  # (c²(α² − 1) + 1) at the edge
    cos2 = (1.0 - root) / (1.0 - a2) if a2 < 1.0 else 0.0
    return math.degrees(math.acos(math.sqrt(min(max(cos2, 0.0), 1.0))))


def coverage_image(counts: np.ndarray, top: int = 8) -> np.ndarray:
    """Highlight counts (NaN or −1: nothing seen) as an 8-bit RGBA image, viridis from 0 to ``top``.

    Zero counts are drawn red so that the texels a schedule misses stand out.
    """
    seen = np.isfinite(counts) & (np.nan_to_num(counts, nan=-1.0) >= 0)
    level = np.clip(np.nan_to_num(counts, nan=0.0) / top, 0.0, 1.0)
    bgr = cv2.applyColorMap((255.0 * level + 0.5).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    rgba = np.zeros((*counts.shape, 4), np.uint8)
    rgba[..., :3] = bgr[..., ::-1]
    rgba[seen & (np.nan_to_num(counts, nan=0.0) < 0.5), :3] = (220, 30, 30)
    rgba[..., 3] = np.where(seen, 255, 0)
    return rgba


def write_coverage(coverages: Sequence[HighlightCoverage], out_dir: str | Path) -> list[Path]:
    """``coverage.json`` (the summaries) and, per roughness, ``coverage-view-α.png`` (the
    camera's view) and ``coverage-uv-α.png`` (the mesh's UV layout, ``v`` up)."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReflectanceError(f"{out}: cannot create the folder ({exc.strerror or exc})") from None
    written = []
    for cover in coverages:
        maps = {"view": cover.counts.astype(float), "uv": cover.texture}
        for name, counts in maps.items():
            if counts is None:
                continue
            path = out / f"coverage-{name}-{cover.roughness:g}.png"
            if not cv2.imwrite(str(path), cv2.cvtColor(coverage_image(counts), cv2.COLOR_RGBA2BGRA)):
                raise ReflectanceError(f"{path}: could not write the PNG")
            written.append(path)
    summary = out / "coverage.json"
    summary.write_text(json.dumps([c.summary() for c in coverages], indent=2) + "\n")
    written.append(summary)
    return written

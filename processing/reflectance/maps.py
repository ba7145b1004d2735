"""The albedo along the object's vertical axis (profiles), and in the mesh's UV space (a texture)."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter

from processing.reflectance.estimate import ReflectanceResult

log = logging.getLogger("mirrorgonio.processing")


def reflectance_profiles(result: ReflectanceResult, bins: int = 24, min_points: int = 5) -> dict[str, Any]:
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
        stats: dict[str, list[float]] = {"median": [], "q25": [], "q75": [], "count": []}
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

    valid = result.valid & np.all(np.isfinite(result.uv), axis=1)
    return splat_uv(result.uv[valid], result.rho_points[method][valid], size, fill)


def splat_uv(uv: np.ndarray, values: np.ndarray, size: int, fill: int = 2) -> np.ndarray:
    """Values (N, C) at UV points splatted into a (size, size, C) texture, NaN where none land.

    ``v`` is up, so row 0 is ``v = 1``; a texel holds the mean of the values that land in
    it; empty texels within ``fill`` texels of filled ones take the mean of their filled
    3 × 3 neighbours (``fill`` passes).
    """
    u = np.mod(uv[:, 0], 1.0)
    v = np.mod(uv[:, 1], 1.0)
    col = np.clip((u * size).astype(int), 0, size - 1)
    row = np.clip(((1.0 - v) * size).astype(int), 0, size - 1)
    flat = row * size + col
    channels = values.shape[1]
    total = np.zeros((size * size, channels))
    count = np.bincount(flat, minlength=size * size).astype(float)
    for c in range(channels):
        total[:, c] = np.bincount(flat, weights=values[:, c], minlength=size * size)
    with np.errstate(divide="ignore", invalid="ignore"):
        texture = (total / count[:, None]).reshape(size, size, channels)
    for _ in range(max(0, int(fill))):
        known = np.all(np.isfinite(texture), axis=-1)
        if known.all() or not known.any():
            break
        weight = uniform_filter(known.astype(float), size=3, mode="constant")
        summed = np.stack(
            [uniform_filter(np.where(known, texture[..., c], 0.0), size=3, mode="constant") for c in range(channels)],
            axis=-1,
        )
        grow = ~known & (weight > 0.5 / 9.0)  # at least one filled neighbour (not round-off)
        texture[grow] = summed[grow] / weight[grow, None]
    return texture

"""What the light report's figures share: every source's samples, the sweep's azimuth, the truth."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from drivers.contracts.runfile import RunFile
from drivers.pose import Pose
from processing.hdr.model import NoiseModel
from processing.lightmodel import LightModel, SourceModel
from processing.report.drawing import COLOURS
from processing.report.markup import FigureEncoder
from processing.trace import (
    ChiefRays,
    RigGeometry,
    ball_pixel_box,
    box_pixels,
    grid_stride,
    light_pose_at,
    trace_pixels,
)

log = logging.getLogger("mirrorgonio.processing")

#: A simulated run's true radiant intensity, ``truth(source, theta)``: the source by its index or
#: its name, θ in radians; it raises LookupError (or TypeError) for a source it does not know.
Truth = Callable[[int | str, np.ndarray], ArrayLike | None]


class SampleColumns(Protocol):
    """What the report reads of the pipeline's samples (``processing.light_run.SourceSamples``):
    one row per position, one column per source."""

    positions: np.ndarray
    theta: np.ndarray
    phi: np.ndarray
    intensity: np.ndarray
    sigma: np.ndarray
    cell_sum: np.ndarray


class RunReport(Protocol):
    """What the report reads of the pipeline's report (``processing.light_run.ProcessReport``)."""

    run_file: Path
    results_file: Path
    noise: NoiseModel
    outputs: dict[str, list[Path]]
    estimator: str
    estimator_reason: str
    spatial_resolution_m: float


@dataclass
class SourceData:
    """One source's samples as plain arrays (NaN where a column is missing)."""

    theta: np.ndarray
    phi: np.ndarray
    intensity: np.ndarray
    sigma: np.ndarray
    position: np.ndarray
    cell_sum: np.ndarray | None


@dataclass
class MiddlePosition:
    """The middle position's chief-ray trace, when the run is at hand."""

    index: int
    pose: Pose
    geometry: RigGeometry
    rays: ChiefRays | None = None
    pixel_polygon: np.ndarray | None = None  # (4, 2) metres on the light plane
    pixel_at: tuple[float, float] | None = None


@dataclass
class ReportContext:
    model: LightModel
    data: list[SourceData]
    azimuth: float  # the sweep's main azimuth φ_s, radians in (−π/2, π/2]
    truth: Truth | None
    resolution_m: float
    colours: list[str] = field(default_factory=list)
    geometry: MiddlePosition | None = None
    geometry_note: str = ""
    encoder: FigureEncoder | None = None


def _column(table: dict[str, Any], key: str) -> np.ndarray | None:
    if key not in table or table[key] is None:
        return None
    return np.asarray([np.nan if v is None else v for v in table[key]], dtype=float)


def source_data(model: LightModel, samples: SampleColumns | None = None) -> list[SourceData]:
    """Every source's samples: the model's tables (what was fitted), else the pipeline's
    :class:`SourceSamples` columns."""
    out = []
    for k, source in enumerate(model.sources):
        table = source.samples or {}
        theta = _column(table, "theta")
        if theta is None and samples is not None:
            ok = np.isfinite(samples.intensity[:, k]) & np.isfinite(samples.theta[:, k])
            cell = np.asarray(samples.cell_sum[:, k], dtype=float)[ok]
            out.append(
                SourceData(
                    np.asarray(samples.theta[:, k])[ok],
                    np.asarray(samples.phi[:, k])[ok],
                    np.asarray(samples.intensity[:, k])[ok],
                    np.asarray(samples.sigma[:, k])[ok],
                    np.asarray(samples.positions)[ok].astype(float),
                    cell,
                )
            )
            continue
        if theta is None:
            empty = np.zeros(0)
            out.append(SourceData(empty, empty, empty, empty, empty, None))
            continue
        n = len(theta)

        def col(key, default=np.nan, table=table, n=n):
            value = _column(table, key)
            return value if value is not None and len(value) == n else np.full(n, default)

        position = _column(table, "position")
        cell = _column(table, "cell_sum_intensity")
        out.append(
            SourceData(
                theta,
                col("phi", 0.0),
                col("intensity"),
                col("sigma"),
                position if position is not None and len(position) == n else np.arange(n, dtype=float),
                cell if cell is not None and len(cell) == n else None,
            )
        )
    return out


def _sweep_azimuth(data: list[SourceData]) -> float:
    """The samples' main azimuth, modulo π (weighted by sin θ: the axis carries no azimuth)."""
    s = c = 0.0
    for d in data:
        ok = np.isfinite(d.theta) & np.isfinite(d.phi)
        w = np.sin(d.theta[ok])
        s += float(np.sum(w * np.sin(2.0 * d.phi[ok])))
        c += float(np.sum(w * np.cos(2.0 * d.phi[ok])))
    if s == 0.0 and c == 0.0:
        return 0.0
    return 0.5 * math.atan2(s, c)  # in (−π/2, π/2]


def in_degrees(angle: float) -> str:
    """An angle in whole degrees (an int: never "-0")."""
    return f"{round(math.degrees(angle)):d}°"


def signed_theta(theta: ArrayLike, phi: ArrayLike, azimuth: float) -> np.ndarray:
    """θ with the sign of its side: + within 90° of the sweep's azimuth, − opposite."""
    theta = np.asarray(theta, dtype=float)
    return np.where(np.cos(np.asarray(phi, dtype=float) - azimuth) >= 0.0, theta, -theta)


def truth_values(truth: Truth | None, k: int, name: str, theta: np.ndarray) -> np.ndarray | None:
    if truth is None:
        return None
    for key in (k, name):
        try:
            value = truth(key, theta)
        except (LookupError, TypeError):
            continue
        if value is None:
            return None
        return np.broadcast_to(np.asarray(value, dtype=float), np.shape(theta)).copy()
    return None


def truth_error(source: SourceModel, truth: Truth | None, k: int) -> float | None:
    """RMS(I_fit − I_true) / max(I_true) over the θ the samples cover (``docs/measurement.md``)."""
    lo, hi = source.fit.theta_range
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return None
    grid = np.linspace(lo, hi, 200)
    true = truth_values(truth, k, source.name, grid)
    if true is None or not np.all(np.isfinite(true)) or np.max(true) <= 0:
        return None
    return math.sqrt(float(np.mean((source.fit(grid) - true) ** 2))) / float(np.max(true))


def report_context(
    model: LightModel,
    *,
    samples: SampleColumns | None = None,
    truth: Truth | None = None,
    resolution_m: float = float("nan"),
) -> ReportContext:
    data = source_data(model, samples)
    colours = [COLOURS[k % len(COLOURS)] for k in range(len(model.sources))]
    return ReportContext(model, data, _sweep_azimuth(data), truth, resolution_m, colours)


def middle_position(run: RunFile, samples: SampleColumns | None) -> MiddlePosition:
    """The sweep's middle position: its index, the light's pose there and the rig's geometry (no ray yet)."""

    rig = run.header.rig
    geometry = RigGeometry.from_rig(rig)
    positions = np.asarray(samples.positions) if samples is not None and len(samples.positions) else None
    if positions is None:
        positions = np.asarray(run.completed_positions())
    if positions.size == 0:
        positions = np.arange(run.n_positions)
    index = int(positions[len(positions) // 2])
    measured = None
    try:
        measured = run.measured_pose(index)
    except (ValueError, KeyError, OSError):
        measured = None
    pose = light_pose_at(geometry, measured if measured is not None else run.header.tool_poses[index])
    return MiddlePosition(index, pose, geometry)


def trace_middle(position: MiddlePosition, model: LightModel, max_pixels: int = 60_000) -> MiddlePosition:
    """``position`` with the chief rays of (at most about ``max_pixels``) pixels across the ball, and the
    footprint on the light plane of the pixel whose chief ray lands nearest the sources."""

    geometry, pose = position.geometry, position.pose
    out = replace(position)
    box = ball_pixel_box(geometry)
    stride = grid_stride(box, max_pixels)
    cols, rows = box_pixels(box, stride)
    rays = trace_pixels(geometry, pose, cols, rows)
    out.rays = rays
    centroid = np.mean([s.centre_m for s in model.sources], axis=0)
    if np.any(rays.valid):
        dist = np.where(rays.valid, np.hypot(rays.u - centroid[0], rays.v - centroid[1]), np.inf)
        i = int(np.argmin(dist))
        col, row = rays.cols[i], rays.rows[i]
        if stride > 1:  # refine on the full pixel grid around the best subsampled pixel
            cc, rr = np.meshgrid(np.arange(col - stride, col + stride + 1), np.arange(row - stride, row + stride + 1))
            fine = trace_pixels(geometry, pose, cc.ravel(), rr.ravel())
            d2 = np.where(fine.valid, np.hypot(fine.u - centroid[0], fine.v - centroid[1]), np.inf)
            j = int(np.argmin(d2))
            col, row = fine.cols[j], fine.rows[j]
        corners = trace_pixels(
            geometry, pose, col + np.array([-0.5, 0.5, 0.5, -0.5]), row + np.array([-0.5, -0.5, 0.5, 0.5])
        )
        if np.all(corners.valid):
            out.pixel_polygon = np.column_stack([corners.u, corners.v])
            out.pixel_at = (float(col), float(row))
    return out

"""The sources' samples over a run: the estimator chosen, the view checked, the rows assembled."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivers.contracts.runfile import RunFile
from drivers.pose import Pose
from processing.light_run.errors import ProcessingError
from processing.light_run.geometry import CameraFit, geometry_and_builder
from processing.light_run.position import SourceRow, SourcesPlan
from processing.options import Estimator
from processing.trace import RigGeometry, ball_pixel_box, light_pose_at_position, trace_pixels
from processing.unmixing.sources import Source
from processing.unmixing.templates import TemplateBuilder

log = logging.getLogger("mirrorgonio.processing")


@dataclass
class SourceSamples:
    """Every source's samples over the run: one row per position."""

    positions: np.ndarray
    theta: np.ndarray  # (n_positions, n_sources)
    phi: np.ndarray
    intensity: np.ndarray  # channel mean
    sigma: np.ndarray
    intensity_rgb: np.ndarray  # (n_positions, n_sources, 3)
    cell_sum: np.ndarray  # (n_positions, n_sources), the fast path on the same data


def assemble_samples(positions: np.ndarray, rows: dict[int, SourceRow], plan: SourcesPlan) -> SourceSamples:
    """The per-position rows, in position order, as the samples of every source."""
    n, m = len(positions), len(plan.layout)
    theta, phi, intensity, sigma = (np.full((n, m), np.nan) for _ in range(4))
    out = SourceSamples(positions, theta, phi, intensity, sigma, np.full((n, m, 3), np.nan), np.full((n, m), np.nan))
    for row, index in enumerate(positions):
        found = rows[int(index)]
        out.theta[row], out.phi[row] = found.theta, found.phi
        out.cell_sum[row] = found.cell_sum
        if plan.estimator is Estimator.CELL_SUMS:
            out.intensity[row] = found.cell_sum
            out.sigma[row] = np.nan
        else:
            out.intensity_rgb[row] = found.intensity_rgb
            out.intensity[row] = np.nanmean(found.intensity_rgb, axis=1)
            out.sigma[row] = np.sqrt(np.nansum(found.sigma_rgb**2, axis=1)) / 3.0
    return out


def choose_estimator(
    geometry: RigGeometry, builder: TemplateBuilder, layout: Sequence[Source], light_pose: Pose, requested: Estimator
) -> tuple[Estimator, str, float]:
    """Templates, or cell sums where the blur's footprint on the light plane is smaller
    than the sources' spacing; returns (estimator, reason, footprint radius in metres)."""

    footprint = float("nan")
    for source in layout:
        template = builder.build(source, light_pose)
        if template is None:
            continue
        col, row = template.image_centre
        rays = trace_pixels(geometry, light_pose, np.array([col, col + 1.0, col]), np.array([row, row, row + 1.0]))
        per_pixel = max(
            math.hypot(rays.u[1] - rays.u[0], rays.v[1] - rays.v[0]),
            math.hypot(rays.u[2] - rays.u[0], rays.v[2] - rays.v[0]),
        )
        footprint = per_pixel * template.blur_radius_px
        break
    spacing = min((math.dist(a.centre, b.centre) for a in layout for b in layout if a is not b), default=math.inf)
    requested = Estimator(requested)
    if requested is not Estimator.AUTO:
        return requested, f"{requested} as requested", footprint
    if not math.isfinite(footprint):
        return Estimator.TEMPLATES, "no source in view to size the footprint", footprint
    size = 2.0 * min(source.radius for source in layout)
    if 2.0 * footprint < spacing and 2.0 * footprint <= 2.0 * size:
        return (
            Estimator.CELL_SUMS,
            (
                f"the footprint ({2e3 * footprint:.2f} mm across) is smaller than the sources' spacing "
                f"({1e3 * spacing:.2f} mm) and comparable to their size: flux sums are exact enough"
            ),
            footprint,
        )
    # Measured: even a lone 2 mm LED under a 13 mm footprint is 3 % off with flux sums
    # (each pixel's chief ray misstates the direction its light left in), so a footprint
    # much larger than the emitters also calls for templates.
    return (
        Estimator.TEMPLATES,
        (
            f"the footprint ({2e3 * footprint:.2f} mm across) exceeds the sources' spacing "
            f"({1e3 * spacing:.2f} mm) or size ({1e3 * size:.2f} mm): unmixing with templates"
        ),
        footprint,
    )


def check_view(
    run: RunFile, geometry: RigGeometry, builder: TemplateBuilder, layout: Sequence[Source], positions: np.ndarray
) -> None:
    """Refuse, in one line, a run the estimate cannot work with (from the geometry alone;
    a run saturated everywhere is refused once its positions are merged)."""

    if ball_pixel_box(geometry) is None:
        raise ProcessingError(f"{run.path}: the ball is not in the camera's view (check camera.pose and ball.centre_m)")
    seen = any(
        builder.build(source, light_pose_at_position(run, geometry, int(i))) is not None
        for i in positions[:: max(1, len(positions) // 8)]
        for source in layout
    )
    if not seen:
        raise ProcessingError(
            f"{run.path}: the light never reflects into the camera at any position (is it facing the ball?)"
        )


def plan_sources(
    run: RunFile,
    layout: Sequence[Source],
    estimator: Estimator,
    ball_centre: Sequence[float] | np.ndarray | None,
    positions: np.ndarray,
    camera: CameraFit | None = None,
) -> SourcesPlan:
    """Check the view and choose the estimator: geometry only, before any position is read."""
    geometry, builder = geometry_and_builder(run, ball_centre, camera)
    check_view(run, geometry, builder, layout, positions)
    middle = int(positions[len(positions) // 2])
    chosen, reason, footprint = choose_estimator(
        geometry, builder, layout, light_pose_at_position(run, geometry, middle), estimator
    )
    log.info("%s: %s", run.path, reason)
    spacing = min((math.dist(a.centre, b.centre) for a in layout for b in layout if a is not b), default=math.inf)
    cell_radius = min(0.5 * spacing, 3.0 * footprint) if math.isfinite(footprint) else 0.5 * spacing
    return SourcesPlan(
        tuple(layout),
        tuple(ball_centre) if ball_centre is not None else None,
        chosen,
        reason,
        footprint,
        cell_radius,
        camera,
    )

"""What a wrong ball position costs: how far the recovered outgoing angles move when the
ball is off where the processing thinks."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from drivers.contracts.rig import Rig
from drivers.pose import Pose
from processing.calibration.errors import CalibrationError
from processing.trace import RigGeometry, ball_pixel_grid, trace_pixels


def _wrapped(angle: np.ndarray) -> np.ndarray:
    return np.abs((angle + math.pi) % (2.0 * math.pi) - math.pi)


def angle_sensitivity(
    rig: Rig, light_pose: Pose, shift_m: float = 1e-3, *, plane_radius_m: float | None = None, max_pixels: int = 250_000
) -> dict[str, Any]:
    """How far the recovered outgoing angles move when the ball is ``shift_m`` off.

    Chief rays of a grid of pixels on the ball are traced (``processing.trace``) with the
    rig's ball centre and with it shifted by ``shift_m`` along each rig axis; the pixels
    kept are those whose ray lands on the light plane within ``plane_radius_m`` of the
    light's axis in both traces (default: the housing's face, or 20 mm without one).

    Returns per axis (``"x"``, ``"y"``, ``"z"``): the median and largest change of θ, of φ
    (where θ > 5°, φ being undefined on the axis), of the direction itself (the angle
    between the two outgoing rays) in degrees, and of (u, v) in mm; and overall
    ``theta_median_deg`` / ``theta_max_deg`` (the largest over the axes), ``pixels``,
    ``shift_mm``.
    """

    if not shift_m > 0:
        raise CalibrationError(f"shift_m must be positive, got {shift_m!r}")
    radius = plane_radius_m if plane_radius_m is not None else (rig.light.housing_radius_m or 0.02)
    geometry = RigGeometry.from_rig(rig)
    cols, rows = ball_pixel_grid(geometry, max_pixels)
    base = trace_pixels(geometry, light_pose, cols, rows)
    on_light = base.valid & (np.hypot(base.u, base.v) <= radius)
    # Only the pixels that see the light are traced again (a fraction of the ball's).
    cols, rows = np.asarray(cols, float).ravel()[on_light], np.asarray(rows, float).ravel()[on_light]
    base_theta, base_phi, base_u, base_v = base.theta[on_light], base.phi[on_light], base.u[on_light], base.v[on_light]

    def direction(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
        return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)

    out: dict[str, Any] = {"shift_mm": shift_m * 1e3, "plane_radius_mm": radius * 1e3}
    pixels = []
    for i, name in enumerate("xyz"):
        centre = np.asarray(rig.ball.centre_m, dtype=float).copy()
        centre[i] += shift_m
        moved = trace_pixels(RigGeometry.from_rig(rig, ball_centre=centre), light_pose, cols, rows)
        use = moved.valid
        if not use.any():
            raise CalibrationError(
                f"no pixel of the ball sees the light within {radius * 1e3:.0f} mm of its axis at this pose"
            )
        d_theta = np.degrees(np.abs(moved.theta[use] - base_theta[use]))
        off_axis = base_theta[use] > math.radians(5.0)
        d_phi = np.degrees(_wrapped(moved.phi[use] - base_phi[use]))[off_axis]
        cosang = np.clip(
            np.sum(direction(moved.theta[use], moved.phi[use]) * direction(base_theta[use], base_phi[use]), axis=1),
            -1,
            1,
        )
        d_dir = np.degrees(np.arccos(cosang))
        d_uv = np.hypot(moved.u[use] - base_u[use], moved.v[use] - base_v[use]) * 1e3
        out[name] = {
            "theta_median_deg": float(np.median(d_theta)),
            "theta_max_deg": float(d_theta.max()),
            "phi_median_deg": float(np.median(d_phi)) if d_phi.size else float("nan"),
            "phi_max_deg": float(d_phi.max()) if d_phi.size else float("nan"),
            "direction_median_deg": float(np.median(d_dir)),
            "direction_max_deg": float(d_dir.max()),
            "uv_median_mm": float(np.median(d_uv)),
            "uv_max_mm": float(d_uv.max()),
            "pixels": int(use.sum()),
        }
        pixels.append(int(use.sum()))
    out["theta_median_deg"] = max(out[a]["theta_median_deg"] for a in "xyz")
    out["theta_max_deg"] = max(out[a]["theta_max_deg"] for a in "xyz")
    out["pixels"] = min(pixels)
    return out

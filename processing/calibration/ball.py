"""The ball's centre from its silhouette and known radius, and the centre against the rig's.

Every silhouette ray is tangent to the sphere: the centre is the least-squares fit of that
cone (:func:`solve_ball_centre`), after the edge points are moved in by the Fresnel rim's
shift (:func:`fresnel_rim_shift_px`: the silhouette's edge estimator applied to a sharp
silhouette's Fresnel profile).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import OptimizeResult, least_squares

from drivers.contracts.rig import Rig
from processing.calibration.errors import CalibrationError
from processing.calibration.silhouette import Silhouette, detect_silhouette, flux_edges


@dataclass
class BallFit:
    """The ball's centre measured from its silhouette.

    Attributes
    ----------
    centre_camera : (3,)
        Centre in camera coordinates (OpenCV: x right, y down, z forward), metres.
    sigma_camera : (3,)
        1-sigma statistical uncertainty per camera axis, metres.
    covariance_camera : (3, 3)
    residuals : (N,)
        Distance from the centre to each (corrected) silhouette ray minus R, metres.
    centre_rig, sigma_rig : (3,) or None
        The same in the rig frame, when the camera's extrinsics were given.
    naive_centre_camera : (3,)
        For comparison: the ellipse centre back-projected, at the distance its apparent
        size gives (what ignoring perspective would report).
    rim_shift_px : float
        Median inward shift applied to the edge points for the Fresnel rim (0 without
        the ball's refractive index).
    points_used : int
    edge_points_px : (N, 2) or None
        The edge points the centre was fitted to (col, row), the rim's shift removed: what a
        later fit of the camera's pose takes as the silhouette measured.
    """

    centre_camera: np.ndarray
    sigma_camera: np.ndarray
    covariance_camera: np.ndarray
    residuals: np.ndarray
    radius_m: float
    centre_rig: np.ndarray | None = None
    sigma_rig: np.ndarray | None = None
    naive_centre_camera: np.ndarray | None = None
    rim_shift_px: float = 0.0
    points_used: int = 0
    edge_points_px: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    @property
    def rms_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))


# --- the centre -----------------------------------------------------------------------------------
def _rays(k_inv: np.ndarray, pts: np.ndarray) -> np.ndarray:
    homogeneous = np.column_stack([pts, np.ones(len(pts))])
    d = homogeneous @ k_inv.T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _cone_guess(d: np.ndarray, radius: float) -> np.ndarray:
    """Closed form: tangent rays satisfy ``d_i · a = cos β``, i.e. ``d_i · w = 1``."""
    w, *_ = np.linalg.lstsq(d, np.ones(len(d)), rcond=None)
    norm = float(np.linalg.norm(w))
    if not norm > 1.0:
        raise CalibrationError("the silhouette rays do not form a cone around a ball")
    sin_beta = math.sqrt(1.0 - 1.0 / norm**2)
    return (w / norm) * radius / sin_beta


def _mean_reflectance(ball_index: tuple[ArrayLike, ArrayLike], cos_i: np.ndarray) -> np.ndarray:
    n, k = (np.atleast_1d(np.asarray(x, dtype=float)) for x in ball_index)
    eta = (n + 1j * k)[None, :]
    c = np.clip(cos_i, 0.0, 1.0)[:, None]
    root = np.sqrt(eta * eta - (1.0 - c * c))
    r_s = (c - root) / (c + root)
    r_p = (eta * eta * c - root) / (eta * eta * c + root)
    return (0.5 * (np.abs(r_s) ** 2 + np.abs(r_p) ** 2)).mean(axis=1)


def fresnel_rim_shift_px(
    kappa: ArrayLike,
    sin_beta: float,
    ball_index: tuple[ArrayLike, ArrayLike],
    window_px: tuple[float, float],
    curvature: float = 0.0,
    line_spread: tuple[np.ndarray, np.ndarray] | None = None,
    step: float = 0.05,
) -> np.ndarray:
    """Outward shift (px) of the flux-balanced edge caused by the Fresnel rim.

    For a sharp silhouette, the profile a pixel ``δ`` inside the edge sees is the ball's
    reflectance ``F(α)`` at the incidence of the ray ``ψ = κ δ`` inside the tangent
    (``κ``: radians per pixel along the normal), where the ray's impact parameter
    ``|C| sin(β - ψ) = R sin α``, blurred by the measured ``line_spread`` (offsets, weights);
    the estimator of :func:`detect_silhouette` applied to that profile gives the shift.
    (The blur matters: it carries the Fresnel curve's dip at 70-80° into the inner window.)
    The smooth parts of the interior (the room, ``cos⁴``) are absorbed by the estimator's
    fitted lines and do not enter.
    """
    kappa = np.atleast_1d(np.asarray(kappa, dtype=float))
    x1, x2 = window_px
    beta = math.asin(sin_beta)
    if line_spread is not None:
        lsf_t, lsf_w = (np.asarray(x, dtype=float) for x in line_spread)
        half = int(math.ceil(np.max(np.abs(lsf_t)) / step))
        kernel = np.interp(np.arange(-half, half + 1) * step, lsf_t, lsf_w, left=0.0, right=0.0)
        kernel = kernel / kernel.sum()
    else:
        half, kernel = 0, np.ones(1)
    reach = x1 + x2 + 2.0 + half * step
    grid = np.arange(-int(math.ceil(reach / step)), int(math.ceil(reach / step)) + 1) * step

    # Cell averages over 16 sub-samples: F rises as sqrt(distance) into the edge.
    sub = grid[:, None] + (np.arange(16) + 0.5 - 8.0)[None, :] * (step / 16.0)
    delta = np.maximum(-sub, 0.0)  # px inside the edge
    psi = kappa[:, None, None] * delta[None, :, :]
    sin_alpha = np.clip(np.sin(np.clip(beta - psi, -math.pi / 2, math.pi / 2)) / sin_beta, -1.0, 1.0)
    cos_alpha = np.sqrt(1.0 - sin_alpha**2)
    reflectance = _mean_reflectance(ball_index, cos_alpha.ravel()).reshape(cos_alpha.shape)
    sharp = np.where(sub[None, :, :] < 0.0, reflectance, 0.0).mean(axis=2)
    blurred = np.stack([np.convolve(row, kernel, mode="same") for row in sharp])

    def profile_at(offsets: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(o, grid, b) for o, b in zip(offsets, blurred, strict=True)])

    shift, *_ = flux_edges(profile_at, kappa.size, x1, x2, step, curvature, iterations=6)
    return shift


def _tangent_fit(d: np.ndarray, start: np.ndarray, radius: float) -> OptimizeResult:
    """Least squares (Levenberg-Marquardt) of the distances from the centre to the rays ``d`` minus R."""

    def residual(c: np.ndarray) -> np.ndarray:
        q = c[None, :] - (d @ c)[:, None] * d
        return np.linalg.norm(q, axis=1) - radius

    def jacobian(c: np.ndarray) -> np.ndarray:
        q = c[None, :] - (d @ c)[:, None] * d
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    return least_squares(residual, start, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)


def _rim_shift(
    silhouette: Silhouette, k_inv: np.ndarray, sin_beta: float, ball_index: tuple[ArrayLike, ArrayLike]
) -> np.ndarray:
    """The Fresnel rim's outward shift (px) at each edge point of a ball of angular radius ``asin(sin_beta)``:
    :func:`fresnel_rim_shift_px` on a grid of the points' radians per pixel along the normal, interpolated."""
    pts = np.asarray(silhouette.points, dtype=float)
    inward = _rays(k_inv, pts - np.asarray(silhouette.normals, dtype=float))
    kappa = np.arccos(np.clip(np.sum(_rays(k_inv, pts) * inward, axis=1), -1.0, 1.0))
    grid = np.linspace(kappa.min(), kappa.max(), 9) if np.ptp(kappa) > 0 else kappa[:1]
    # A straight edge blurred in 1-D, so no curvature weighting: the detection's
    # weighting undoes the 2-D blur of the curved outline, which the model lacks.
    per_grid = fresnel_rim_shift_px(grid, sin_beta, ball_index, silhouette.window_px, 0.0, silhouette.line_spread)
    return np.interp(kappa, grid, per_grid) if grid.size > 1 else np.full(len(pts), per_grid[0])


def solve_ball_centre(
    silhouette: Silhouette,
    camera_matrix: ArrayLike,
    radius_m: float,
    *,
    extrinsics: tuple[np.ndarray, np.ndarray] | None = None,
    ball_index: tuple[ArrayLike, ArrayLike] | None = None,
    iterations: int = 3,
) -> BallFit:
    """The ball's centre from its silhouette and known radius.

    Every silhouette ray is tangent to the sphere: for each edge point's back-projected
    unit ray d_i the distance from the centre C to the ray, ``|C - (C·d_i) d_i|``, equals
    R. Solved by ``scipy.optimize.least_squares`` from the closed-form cone fit
    (``d_i · w = 1``, the cone's axis ``w / |w|`` and half-angle ``arccos(1 / |w|)``).

    Parameters
    ----------
    silhouette : Silhouette
    camera_matrix : (3, 3)
        OpenCV intrinsics K (no lens distortion).
    radius_m : float
        The ball's radius.
    extrinsics : (R, t), optional
        ``x_cam = R X + t``: also report the centre in the rig frame.
    ball_index : (n, k), optional
        The ball's complex refractive index (per channel; the reflectances are averaged):
        corrects the edge points for the Fresnel rim (see the module's notes). Without
        it the edge lies outside the tangent and the ball comes out too close.

    Raises
    ------
    CalibrationError
        Too few edge points, or rays that do not graze one ball.
    """
    pts = np.asarray(silhouette.points, dtype=float)
    if len(pts) < 10:
        raise CalibrationError(f"only {len(pts)} silhouette points: at least 10 are needed")
    k_inv = np.linalg.inv(np.asarray(camera_matrix, dtype=float))
    radius = float(radius_m)
    d = _rays(k_inv, pts)
    result = _tangent_fit(d, _cone_guess(d, radius), radius)
    shift, use = np.zeros(len(pts)), pts
    if ball_index is not None and silhouette.window_px[0] > 0:
        normals = np.asarray(silhouette.normals, dtype=float)
        for _ in range(iterations):  # the rim's shift depends on the ball's distance
            shift = _rim_shift(silhouette, k_inv, radius / float(np.linalg.norm(result.x)), ball_index)
            use = pts - shift[:, None] * normals
            result = _tangent_fit(_rays(k_inv, use), result.x, radius)
    centre, residuals = result.x, result.fun
    s2 = float(residuals @ residuals) / max(len(pts) - 3, 1)
    try:
        covariance = s2 * np.linalg.inv(result.jac.T @ result.jac)
    except np.linalg.LinAlgError:
        raise CalibrationError("the silhouette does not constrain the ball's centre (degenerate geometry)") from None
    if not np.all(np.isfinite(centre)) or centre[2] <= radius:
        raise CalibrationError("the silhouette rays do not graze a ball in front of the camera")
    # The naive answer, for comparison: the ellipse's centre taken for the ball's.
    axis = _rays(k_inv, np.asarray([silhouette.ellipse.centre]))[0]
    half = float(np.median(np.arccos(np.clip(_rays(k_inv, use) @ axis, -1.0, 1.0))))
    fit = BallFit(
        centre_camera=centre,
        sigma_camera=np.sqrt(np.diag(covariance)),
        covariance_camera=covariance,
        residuals=residuals,
        radius_m=radius,
        naive_centre_camera=axis * radius / math.sin(half),
        rim_shift_px=float(np.median(shift)),
        points_used=len(pts),
        edge_points_px=use,
    )
    if extrinsics is not None:
        rot, t = (np.asarray(x, dtype=float) for x in extrinsics)
        fit.centre_rig = rot.T @ (centre - t)
        fit.sigma_rig = np.sqrt(np.diag(rot.T @ covariance @ rot))
    return fit


def calibrate_ball(image: ArrayLike, rig: Rig, *, method: str = "ellipse") -> BallFit:
    """Silhouette and centre in one call, with the rig's intrinsics, extrinsics and ball."""
    silhouette = detect_silhouette(image, method=method)
    fit = solve_ball_centre(
        silhouette,
        rig.camera.camera_matrix(),
        rig.ball.radius_m,
        extrinsics=rig.camera.pose.extrinsics(),
        ball_index=(rig.ball.n, rig.ball.k),
    )
    fit.extra["silhouette"] = silhouette
    return fit


def compare_with_rig(fit: BallFit, rig: Rig) -> dict[str, Any]:
    """The measured centre against the rig description's, in millimetres.

    Returns ``measured_mm`` and ``described_mm`` (rig frame), ``discrepancy_mm`` (measured
    minus described, rig frame), ``discrepancy_camera_mm`` (the same along the camera's
    axes: z is the depth), ``distance_mm``, ``sigma_mm`` (the measurement's 1-sigma per rig
    axis) and ``significance`` (the distance over the uncertainty along it).
    """
    rot, t = rig.camera.pose.extrinsics()
    measured = rot.T @ (np.asarray(fit.centre_camera) - t)
    described = np.asarray(rig.ball.centre_m, dtype=float)
    delta = measured - described
    distance = float(np.linalg.norm(delta))
    cov_rig = rot.T @ fit.covariance_camera @ rot
    if distance > 0:
        along = delta / distance
        sigma_along = math.sqrt(max(float(along @ cov_rig @ along), 1e-300))
    else:
        sigma_along = float("nan")
    return {
        "measured_mm": (measured * 1e3).tolist(),
        "described_mm": (described * 1e3).tolist(),
        "discrepancy_mm": (delta * 1e3).tolist(),
        "discrepancy_camera_mm": ((rot @ delta) * 1e3).tolist(),
        "distance_mm": distance * 1e3,
        "sigma_mm": (np.sqrt(np.diag(cov_rig)) * 1e3).tolist(),
        "significance": distance / sigma_along if distance > 0 else 0.0,
    }

"""The ball's silhouette on a run's ambient calibration frames, as a term of the rig's fit.

Every ray through an edge point of the silhouette grazes the ball (:mod:`processing.calibration`),
so for a camera (intrinsics and pose) and a ball, each edge point has a miss: the distance
from the ball's centre to its ray, less the radius. The rig as described misses by what its
pose is off; the fit of the rig keeps the misses at their noise. This measures the camera's
pose relative to the ball directly, with no model of the light: the ball's image placed to
a few hundredths of a pixel, its apparent size to a few thousandths, where the sweep's
templates leave the camera's distance and the light's nearly interchangeable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from drivers.contracts.runfile import CalibrationFrames, RunFile
from processing.calibration import CalibrationError, detect_silhouette, mosaic_luminance, solve_ball_centre
from processing.rig_fit.correction import FITTED, RigCorrection
from processing.trace import RigGeometry

#: The edge points' systematic error, pixels, added in quadrature to their scatter: the Fresnel
#: rim's correction and the profile estimator leave about this much on the simulator.
EDGE_SYSTEMATIC_PX = 0.02

#: The share of pixels at the white level above which a frame is taken as too bright to use.
SATURATED_SHARE = 1e-4


@dataclass(frozen=True)
class SilhouetteTerm:
    """The ball's outline measured: the edge points (col, row; the rim's shift removed) and
    the 1σ of each one's miss (metres at the ball), from which set of frames."""

    points_px: np.ndarray
    sigma_m: float
    frames: str

    def misses(self, geometry: RigGeometry) -> np.ndarray:
        """Each edge point's ray's distance from the ball's centre less its radius (metres)."""
        homogeneous = np.column_stack([self.points_px, np.ones(len(self.points_px))])
        rays = homogeneous @ geometry.K_inv.T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        centre = geometry.R @ geometry.ball_centre + geometry.t
        along = rays @ centre
        return np.linalg.norm(centre[None, :] - along[:, None] * rays, axis=1) - geometry.ball_radius

    def residuals(self, geometry: RigGeometry) -> np.ndarray:
        """The misses in σ."""
        return self.misses(geometry) / self.sigma_m

    def record(self, geometry: RigGeometry) -> dict:
        misses = self.misses(geometry)
        return {
            "frames": self.frames,
            "edge_points": len(misses),
            "sigma_um": round(1e6 * self.sigma_m, 3),
            "rms_miss_sigma": round(float(np.sqrt(np.mean((misses / self.sigma_m) ** 2))), 3),
        }


def silhouette_term(run: RunFile, geometry: RigGeometry, when: str = "before") -> SilhouetteTerm | None:
    """The silhouette measured on the run's ambient frames taken ``when`` (None: the run has none).

    The frame used is the longest exposure that leaves the image unsaturated; its edge points
    are fitted once through the rig as described (the Fresnel rim's shift depends on the
    geometry only slowly), and their scatter about that fit is their noise.

    Raises
    ------
    CalibrationError
        The frames hold no silhouette that can be measured (one line, naming the run).
    """
    frames = run.calibration_frames("ambient", when)
    if frames is None:
        return None
    try:
        image = mosaic_luminance(_best_frame(frames), frames.black_level)
        outline = detect_silhouette(image)
        fit = solve_ball_centre(
            outline,
            geometry.K,
            geometry.ball_radius,
            extrinsics=(geometry.R, geometry.t),
            ball_index=(geometry.n, geometry.k),
        )
    except CalibrationError as exc:
        raise CalibrationError(f"{run.path}: the ambient frames taken {when}: {exc}") from None
    assert fit.edge_points_px is not None  # solve_ball_centre gives them
    distance = float(np.linalg.norm(fit.centre_camera))
    systematic = EDGE_SYSTEMATIC_PX * distance / geometry.K[0, 0]
    return SilhouetteTerm(fit.edge_points_px, math.hypot(fit.rms_m, systematic), f"ambient, {when}")


def _best_frame(frames: CalibrationFrames) -> np.ndarray:
    """The longest exposure with (nearly) no pixel at the white level."""
    order = np.argsort(frames.exposures_s)[::-1]
    for index in order:
        frame = frames.frames[index]
        if np.count_nonzero(frame >= frames.white_level) <= SATURATED_SHARE * frame.size:
            return frame
    return frames.frames[order[-1]]


def coarse_correction(term: SilhouetteTerm, geometry: RigGeometry, limit: np.ndarray) -> RigCorrection:
    """The camera's yaw, pitch and distance that put the described ball on the silhouette
    (the rest as described), within ``limit`` (the fit's bounds, :func:`~processing.rig_fit.correction.bounds`):
    a start from which the local fit of the sweep reaches the right minimum, where an error of
    the ball's image by ten pixels would leave it in another."""
    names = [number.name for number in FITTED]
    moved = [names.index(name) for name in ("camera_yaw", "camera_pitch", "camera_distance")]

    def correction(x: np.ndarray) -> RigCorrection:
        vector = np.zeros(len(FITTED))
        vector[moved] = x
        return RigCorrection.of(vector, np.zeros(3))

    result = least_squares(
        lambda x: term.residuals(correction(x).apply(geometry)),
        np.zeros(3),
        bounds=(-limit[moved], limit[moved]),
        x_scale=limit[moved],
    )
    return correction(result.x)

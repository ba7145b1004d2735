"""The rig's numbers and the sources' places fitted together: the templates' χ² over a few merged
positions as the rig's correction and the layout move, and the ball's silhouette where a run
has calibration frames.

Variable projection as in :class:`~processing.unmixing.problem.LayoutProblem`: every evaluation
solves the sources' intensities (NNLS per position and channel), so the parameters are the
correction of the rig (:class:`~processing.rig_fit.correction.RigCorrection`), the sources'
centres and their common radius.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.pose import Pose
from processing.rig_fit.correction import FITTED, RigCorrection
from processing.trace import RigGeometry, light_pose_at
from processing.unmixing.problem import LayoutProblem


@dataclass(frozen=True)
class SilhouetteTerm:
    """The ball's image measured on calibration frames: its centre and apparent radius in pixels,
    each with its 1σ; the fit keeps the rig's prediction of them there."""

    centre_px: tuple[float, float]
    radius_px: float
    sigma_px: tuple[float, float, float]

    def residuals(self, geometry: RigGeometry) -> np.ndarray:
        """(predicted − measured) / σ for the centre's x, y and the radius."""
        centre, radius = ball_image(geometry)
        measured = np.array([*self.centre_px, self.radius_px])
        return (np.array([*centre, radius]) - measured) / np.asarray(self.sigma_px)


def ball_image(geometry: RigGeometry) -> tuple[np.ndarray, float]:
    """Where the rig puts the ball's image: the projection of its centre (pixels) and the
    apparent radius of its silhouette, ``f·tan(asin(R/d))`` in pixels."""
    centre = geometry.project(geometry.ball_centre[None, :])[0]
    distance = float(np.linalg.norm(geometry.ball_centre - geometry.camera_centre))
    radius = geometry.K[0, 0] * np.tan(np.arcsin(min(1.0, geometry.ball_radius / distance)))
    return centre, float(radius)


class RigProblem:
    """The weighted residuals of the data (and the silhouette) for a correction of the rig, the
    sources' centres (S, 2) and their common radius, over ``problem``'s fixed pixels.

    ``tools`` are the arm's tool poses of ``problem``'s positions (the data it was made from, in
    order): the light's poses follow the corrected arm frame. ``light_axis`` is the direction the
    correction's ``arm_along`` moves the arm (the light's axis, rig frame).
    """

    def __init__(
        self,
        problem: LayoutProblem,
        geometry: RigGeometry,
        tools: list[Pose],
        light_axis: np.ndarray,
        silhouette: SilhouetteTerm | None = None,
    ):
        self.problem, self.geometry, self.tools = problem, geometry, tools
        self.light_axis = np.asarray(light_axis, float)
        self.silhouette = silhouette
        self.correction: RigCorrection | None = None

    def set_correction(self, correction: RigCorrection) -> RigGeometry:
        """Build the templates through the rig so corrected; the corrected geometry."""
        geometry = correction.apply(self.geometry)
        if correction != self.correction:
            self.problem.set_geometry(geometry, key=correction)
            self.problem.set_poses([light_pose_at(geometry, tool) for tool in self.tools])
            self.correction = correction
        return geometry

    def residuals(self, correction: RigCorrection, centres: np.ndarray, radius: float) -> np.ndarray:
        geometry = self.set_correction(correction)
        templates = self.problem.solve(centres, radius)[0]
        if self.silhouette is None:
            return templates
        return np.concatenate([templates, self.silhouette.residuals(geometry)])

    def split(self, x: np.ndarray) -> tuple[RigCorrection, np.ndarray, float]:
        """A vector of the fit (the correction in its units, the centres and radius in mm) unpacked."""
        n = len(FITTED)
        return RigCorrection.of(x[:n], self.light_axis), x[n:-1].reshape(-1, 2) * 1e-3, float(x[-1]) * 1e-3

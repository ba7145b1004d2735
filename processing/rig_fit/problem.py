"""The rig's numbers and the sources' places fitted together: the templates' χ² over a few merged
positions as the rig's correction and the layout move, and the ball's silhouette where a run
has calibration frames.

Variable projection as in :class:`~processing.unmixing.problem.LayoutProblem`: every evaluation
solves the sources' intensities (NNLS per position and channel), so the parameters are the
correction of the rig (:class:`~processing.rig_fit.correction.RigCorrection`), the sources'
centres and their common radius.
"""

from __future__ import annotations

import numpy as np

from drivers.pose import Pose
from processing.rig_fit.correction import RigCorrection
from processing.rig_fit.silhouette import SilhouetteTerm
from processing.trace import RigGeometry, light_pose_at
from processing.unmixing.problem import LayoutProblem


class RigProblem:
    """The weighted residuals of the data (and the silhouette) for a correction of the rig, the
    sources' centres (S, 2) and their common radius, over ``problem``'s fixed pixels.

    ``prior`` is each fitted number's 1σ before the data (the rig's tolerance), or None.
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
        prior: np.ndarray | None = None,
    ):
        self.problem, self.geometry, self.tools = problem, geometry, tools
        self.light_axis = np.asarray(light_axis, float)
        self.silhouette = silhouette
        self.prior = prior
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
        """The templates' weighted residuals, then the silhouette's misses in σ, then each fitted
        number over its ``prior`` 1σ (the description's word, where the data say little)."""
        geometry = self.set_correction(correction)
        parts = [self.problem.solve(centres, radius)[0]]
        if self.silhouette is not None:
            parts.append(self.silhouette.residuals(geometry))
        if self.prior is not None:
            parts.append(correction.vector / self.prior)
        return np.concatenate(parts)

"""The rig's numbers fitted to the data: self-calibration.

A lab describes its rig to a millimetre and a degree; the sweep's images and the ball's
silhouette measure it better. :mod:`~processing.rig_fit.correction` says which numbers the data
can correct and which they cannot tell apart (held, with the reason),
:mod:`~processing.rig_fit.problem` sets up the templates' χ² (and the silhouette's) as the
correction and the sources' places move, and :mod:`~processing.rig_fit.fit` fits them.
"""

from processing.rig_fit.correction import FITTED, HELD, RigCorrection, fitted_rig
from processing.rig_fit.fit import RigFit, fit_rig
from processing.rig_fit.silhouette import SilhouetteTerm, coarse_correction, silhouette_term

__all__ = [
    "FITTED",
    "HELD",
    "RigCorrection",
    "RigFit",
    "SilhouetteTerm",
    "coarse_correction",
    "fit_rig",
    "fitted_rig",
    "silhouette_term",
]

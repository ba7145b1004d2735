"""Whether a light model can be trusted: the templates against every merged position.

The estimate unmixes every position of the sweep with the sources and the rig as settled, and
each position's weighted χ² over its pixels says how well they explain its light; with the
per-pixel σ from the HDR merge's variance, a model that explains the data to their noise
gives χ²/pixel 1. The rig's self-calibration fits five positions; the other sixty are a test it
did not see: a rig still off, or sources that are not there, show at the positions between.

The rule (``docs/light-model.md``): the model is ``suspect`` where

- the sweep's χ²/pixel exceeds :data:`CHI2_ALLOWANCE` (the templates' own model error leaves
  1.06 with the rig described exactly, on the simulator), or
- a tenth of the positions exceed :data:`CHI2_POSITION_ALLOWANCE` (a misfit that comes and goes
  along the sweep, which the average hides), or
- a number the self-calibration fitted ended at its tolerance's bound (the description is
  further off than it says, or something else is wrong), or
- the ball's silhouette is missed by more than :data:`SILHOUETTE_ALLOWANCE` of its noise.

Otherwise ``ok``. The light model's JSON (``quality``), the command line, the report's banner
and the job's note all say which, and why.
"""

from __future__ import annotations

import numpy as np

from processing.light_run.position import SourceRow
from processing.light_run.records import Quality, RigCalibration

#: χ²/pixel over the sweep above which a light model is suspect: the templates leave 1.06 with
#: the rig exact (their own model error); a rig 0.05° or 1 px off leaves 1.09 or more.
CHI2_ALLOWANCE = 1.12

#: χ²/pixel above which a position is counted as unexplained.
CHI2_POSITION_ALLOWANCE = 1.25

#: The share of unexplained positions above which the model is suspect.
UNEXPLAINED_SHARE = 0.1

#: The RMS of the silhouette's misses, in their σ, above which the fitted camera is suspect.
SILHOUETTE_ALLOWANCE = 3.0


def judge(rows: dict[int, SourceRow], calibration: RigCalibration | None) -> Quality:
    """The verdict on the sources estimated at ``rows`` (the module's rule)."""
    chi2 = np.array([row.chi2 for row in rows.values()])
    dof = np.array([row.dof for row in rows.values()])
    fitted = dof > 0
    overall = float(chi2[fitted].sum() / dof[fitted].sum()) if fitted.any() else float("nan")
    per_position = np.where(fitted, chi2 / np.maximum(dof, 1.0), 0.0)
    unexplained = tuple(int(i) for i, value in zip(rows, per_position, strict=True) if value > CHI2_POSITION_ALLOWANCE)
    reasons = []
    if not overall <= CHI2_ALLOWANCE:
        reasons.append(
            f"the templates explain the sweep only to χ²/pixel {overall:.3f} (allowed {CHI2_ALLOWANCE}): the rig or "
            "the sources are not what the data show"
        )
    if len(unexplained) > UNEXPLAINED_SHARE * max(1, int(fitted.sum())):
        reasons.append(
            f"{len(unexplained)} of {int(fitted.sum())} positions are unexplained (χ²/pixel above "
            f"{CHI2_POSITION_ALLOWANCE}): the misfit moves along the sweep"
        )
    if calibration is not None:
        if calibration.fit.at_bound:
            reasons.append(
                f"the self-calibration ended at the tolerance's bound for {', '.join(calibration.fit.at_bound)}: "
                "the rig is further off than its tolerances say, or something else is"
            )
        miss = calibration.fit.silhouette.get("rms_miss_sigma")
        if miss is not None and miss > SILHOUETTE_ALLOWANCE:
            reasons.append(
                f"the fitted camera misses the ball's silhouette by {miss:.1f} σ (RMS): the camera's intrinsics "
                "or the ball's radius are off"
            )
    return Quality(
        "suspect" if reasons else "ok", tuple(reasons), overall, unexplained, int(fitted.sum()), CHI2_ALLOWANCE
    )

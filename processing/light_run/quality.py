"""Whether a light model can be trusted: the templates against every merged position.

The estimate unmixes every position of the sweep with the sources and the rig as settled, and
each position's weighted χ² over its pixels says how well they explain its light; with the
per-pixel σ from the HDR merge's variance, a model that explains the data to their noise
gives χ²/pixel 1. The rig's self-calibration fits five positions; the other sixty are a test it
did not see: a rig still off, or sources that are not there, show at the positions between.

The misfit beyond the noise is read as the templates' relative error ε: a template a fraction ε
off adds ``ε² Σ(m/σ)²`` to χ² (``m`` the model, ``σ`` the HDR merge's noise), so
``ε = √(max(0, χ² − dof) / Σ(m/σ)²)`` (:func:`model_error`). Unlike χ²/pixel, ε does not grow
with the signal-to-noise ratio or the pixels' size: the same rule holds for every rig and
exposure. The rule (``docs/light-model.md``): the model is ``suspect`` where

- the sweep's ε exceeds :data:`MODEL_ERROR_ALLOWANCE`, or
- a tenth of the positions exceed :data:`POSITION_ALLOWANCE` (a misfit that comes and goes
  along the sweep, which the average hides), or
- ε at the sweep's ends, beyond the positions the layout and the rig were fitted to, exceeds
  :data:`OUTSIDE_RATIO` times ε between them (a fit that explains only what it saw), or
- a number the self-calibration fitted ended at its tolerance's bound (the description is
  further off than it says, or something else is wrong), or
- the ball's silhouette is missed by more than :data:`SILHOUETTE_ALLOWANCE` of its noise.

Otherwise ``ok``. The light model's JSON (``quality``), the command line, the report's banner
and the job's note all say which, and why.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from processing.light_run.position import SourceRow
from processing.light_run.records import Quality, RigCalibration

#: The templates' relative error over the sweep above which a light model is suspect.
MODEL_ERROR_ALLOWANCE = 0.03

#: The templates' error at the sweep's ends, beyond the positions the fits used, may exceed this
#: many times their error between those positions, plus :data:`OUTSIDE_MARGIN`, before the model
#: is suspect. With the rig right it is 1.2-1.4 times (the ends see the sources more obliquely);
#: a layout or a rig fitted into a wrong minimum explains the positions it was fitted to and
#: fails beyond them (4-6 times on the demo rig, the principal point 3 px off and no silhouette).
OUTSIDE_RATIO = 1.5
OUTSIDE_MARGIN = 0.001

#: The relative error above which a position is counted as unexplained.
POSITION_ALLOWANCE = 0.06

#: The share of unexplained positions above which the model is suspect.
UNEXPLAINED_SHARE = 0.1

#: The RMS of the silhouette's misses, in their σ, above which the fitted camera is suspect.
SILHOUETTE_ALLOWANCE = 3.0


def judge(
    rows: dict[int, SourceRow], calibration: RigCalibration | None, fit_positions: Sequence[int] | None = None
) -> Quality:
    """The verdict on the sources estimated at ``rows`` (the module's rule). ``fit_positions``:
    the positions the sources and the rig were fitted to (their span is the inside)."""
    order = sorted(rows)
    chi2 = np.array([rows[i].chi2 for i in order])
    dof = np.array([rows[i].dof for i in order])
    signal = np.array([rows[i].signal for i in order])
    fitted = (dof > 0) & (signal > 0)
    overall = float(chi2[fitted].sum() / dof[fitted].sum()) if fitted.any() else float("nan")
    sweep_error = model_error(chi2[fitted].sum(), dof[fitted].sum(), signal[fitted].sum())
    per_position = [model_error(c, d, g) if ok else 0.0 for c, d, g, ok in zip(chi2, dof, signal, fitted, strict=True)]
    unexplained = tuple(i for i, value in zip(order, per_position, strict=True) if value > POSITION_ALLOWANCE)
    reasons = []
    inside_outside = None
    if fit_positions:
        inside = (np.array(order) >= min(fit_positions)) & (np.array(order) <= max(fit_positions)) & fitted
        outside = ~inside & fitted
        if inside.any() and outside.any():
            within = model_error(chi2[inside].sum(), dof[inside].sum(), signal[inside].sum())
            beyond = model_error(chi2[outside].sum(), dof[outside].sum(), signal[outside].sum())
            inside_outside = (within, beyond)
            if beyond > OUTSIDE_RATIO * within + OUTSIDE_MARGIN:
                reasons.append(
                    f"the templates miss {100 * beyond:.1f} % of the light at the sweep's ends, beyond the positions "
                    f"the fits used, against {100 * within:.1f} % between them: what was fitted explains its own "
                    "positions only (sources that are not there, or the rig in a wrong minimum)"
                )
    if not sweep_error <= MODEL_ERROR_ALLOWANCE:
        reasons.append(
            f"the templates miss the sweep's light by {100 * sweep_error:.1f} % of it (χ²/pixel {overall:.3f}; "
            f"allowed {100 * MODEL_ERROR_ALLOWANCE:.0f} %): the rig or the sources are not what the data show"
        )
    if len(unexplained) > UNEXPLAINED_SHARE * max(1, int(fitted.sum())):
        reasons.append(
            f"{len(unexplained)} of {int(fitted.sum())} positions are unexplained (the templates miss more than "
            f"{100 * POSITION_ALLOWANCE:.0f} % of their light): the misfit moves along the sweep"
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
        "suspect" if reasons else "ok",
        tuple(reasons),
        overall,
        sweep_error,
        unexplained,
        int(fitted.sum()),
        MODEL_ERROR_ALLOWANCE,
        inside_outside,
        tuple(round(float(e), 5) for e in per_position),
    )


def model_error(chi2: float, dof: float, signal: float) -> float:
    """The templates' relative error ε that the misfit beyond the noise stands for:
    ``χ² = dof + ε² Σ(m/σ)²``, so ``ε = √(max(0, χ² − dof) / Σ(m/σ)²)``.

    Examples
    --------
    >>> round(model_error(1100.0, 1000.0, 40000.0), 3)  # 100 of excess χ² over a signal of 4e4: 5 %
    0.05
    >>> model_error(990.0, 1000.0, 40000.0)  # within the noise
    0.0
    """
    if signal <= 0:
        return 0.0
    return float(np.sqrt(max(0.0, chi2 - dof) / signal))

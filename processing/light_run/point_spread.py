"""The point spread refined from the merged positions (:mod:`processing.unmixing.point_spread_fit`),
one task on the cluster: estimated at the fits' positions, judged at the positions between them."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from drivers.contracts.runfile import RunFile
from processing.light_run.errors import open_run
from processing.light_run.from_data import FIT_FRACTIONS, BallCentre, PathArg, layout_data, spread_over
from processing.light_run.geometry import CameraFit
from processing.light_run.position import prepare_task
from processing.parallel import Compute
from processing.unmixing.point_spread_fit import PointSpreadRefinement, refine_point_spread
from processing.unmixing.sources import Source

#: Where the refinement is judged: halfway between the fits' positions, so on none of them.
HELD_OUT_FRACTIONS = (1 / 12, 3 / 12, 5 / 12, 7 / 12, 9 / 12, 11 / 12)

#: Why a sweep's point spread is not refined when it is short.
TOO_FEW = "{} merged positions: too few to judge a refinement on positions it did not see"


def refinement_positions(positions: ArrayLike) -> tuple[list[int], list[int]] | None:
    """The positions the refinement is estimated at and those it is judged at, or None where the
    sweep has too few merged positions for both (the second set must hold none of the first)."""
    positions = np.asarray(positions)
    train, held = spread_over(positions, FIT_FRACTIONS), spread_over(positions, HELD_OUT_FRACTIONS)
    if set(train) & set(held) or len(held) < len(HELD_OUT_FRACTIONS):
        return None
    return train, held


def point_spread_from_data(
    run: RunFile,
    results_file: PathArg,
    positions: ArrayLike,
    layout: Sequence[Source],
    ball_centre: BallCentre,
    compute: Compute | None,
    camera: CameraFit | None,
    *,
    force: bool = False,
) -> PointSpreadRefinement:
    """The correction of the templates' point spread the merged ``positions`` support, with the
    sources of ``layout`` and the camera as ``camera`` has it (``force``: estimated whatever the
    templates' χ², kept if it lowers the held-out positions' at all)."""
    picks = refinement_positions(positions)
    if picks is None:
        return PointSpreadRefinement(None, False, TOO_FEW.format(np.asarray(positions).size))
    train, held = picks
    args = (str(run.path), str(results_file), ball_centre, tuple(train), tuple(held), tuple(layout), camera, force)
    compute = compute or Compute()
    return compute.submit(_refined, *args).result() if compute.dask else _refined(*args)


def _refined(
    run_path: str,
    results_file: str,
    ball_centre: BallCentre,
    train: tuple[int, ...],
    held: tuple[int, ...],
    layout: tuple[Source, ...],
    camera: CameraFit | None,
    force: bool,
) -> PointSpreadRefinement:
    """:func:`processing.unmixing.point_spread_fit.refine_point_spread` at those positions (a task)."""
    prepare_task()

    with open_run(run_path) as run:
        train_data, builder, cfa = layout_data(run, results_file, ball_centre, train, camera)
        held_data, _, _ = layout_data(run, results_file, ball_centre, held, camera)
    return refine_point_spread(train_data, held_data, builder, cfa, list(layout), force=force)

"""The noise model a run's merge is weighted with: the rig's, or estimated from its brackets."""

from __future__ import annotations

import logging

import numpy as np

from drivers.contracts.runfile import RunFile
from processing.hdr.model import HDRError, NoiseModel
from processing.hdr.noise import estimate_noise
from processing.light_run.errors import ProcessingError, open_run
from processing.light_run.position import prepare_task
from processing.parallel import Compute
from processing.radiometry import gain_mismatch, radiometric_gain, rig_noise

log = logging.getLogger("mirrorgonio.processing")


def report_gain_mismatch(run: RunFile, noise: NoiseModel) -> None:
    said = gain_mismatch(noise, radiometric_gain(run))
    if said is not None:
        log.log(said[0], "%s: %s", run.path, said[1])


def _noise_estimate_at(index: int, run_path: str) -> NoiseModel | None:
    """One position's noise estimate (a task: opens the run itself); None if its bracket allows none."""
    prepare_task()
    with open_run(run_path) as run:
        if len(run.exposures(index)) < 2:
            return None
        try:
            return estimate_noise(
                run.frames(index),
                run.exposures(index),
                run.black_level(index)[0],
                white_level=int(run.white_level(index)[0]),
            )
        except HDRError as exc:
            log.info("position %d: %s", index, exc)
            return None


def choose_noise(run: RunFile, positions: np.ndarray, mode: str, compute: Compute | None = None) -> NoiseModel:
    """The noise model: the rig's figures, or estimated from the brackets (median over a
    few positions), falling back to the rig's with the reason logged."""
    from_rig = rig_noise(run)
    if mode == "rig":
        return from_rig
    sample = positions[np.linspace(0, len(positions) - 1, min(5, len(positions))).astype(int)]
    found: dict[int, NoiseModel | None] = {}
    (compute or Compute()).map_unordered(
        _noise_estimate_at, [int(i) for i in sample], str(run.path), on_result=found.__setitem__
    )
    estimates = [estimate for i in sample if (estimate := found.get(int(i))) is not None]
    if not estimates:
        if mode == "estimated":
            raise ProcessingError(f"{run.path}: the noise model cannot be estimated from these brackets")
        log.warning("%s: noise model from the rig: the brackets did not allow an estimate", run.path)
        return from_rig
    gain = float(np.median([e.gain_e_per_dn for e in estimates]))
    read = float(np.median([e.read_noise_dn for e in estimates]))
    return NoiseModel(gain, read, source="estimated")

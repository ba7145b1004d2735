"""The offline processing of one run file, step by step, position by position.

Steps (``--steps``): ``hdr`` — merge each position's bracket (``processing.hdr``) and
write the results file, an OpenEXR and a PNG preview per position. Later steps (trace,
fit) build on the results file.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from acquisition.runfile import RunFile, RunFileError
from processing.hdr import HDRError, NoiseModel, estimate_noise, merge_raw, superpixels
from processing.images import write_exr, write_png
from processing.results import HDRInfo, ResultsWriter, results_path_for

log = logging.getLogger("mirrorgonio.processing")
STEPS = ("hdr",)


class ProcessingError(ValueError):
    """A run that cannot be processed (one line naming the file and the cause)."""


@dataclass
class ProcessReport:
    run_file: Path
    results_file: Path
    positions: int
    noise: NoiseModel
    outputs: dict[str, list[Path]] = field(default_factory=dict)
    saturated_pixels: int = 0


def rig_noise(run: RunFile) -> NoiseModel:
    cam = run.header.rig.camera
    return NoiseModel(cam.gain_e_per_dn, cam.read_noise_e / cam.gain_e_per_dn, source="rig")


def choose_noise(run: RunFile, positions: np.ndarray, mode: str) -> NoiseModel:
    """The noise model: the rig's figures, or estimated from the brackets (median over a
    few positions), falling back to the rig's with the reason logged."""
    from_rig = rig_noise(run)
    if mode == "rig":
        return from_rig
    sample = positions[np.linspace(0, len(positions) - 1, min(5, len(positions))).astype(int)]
    estimates = []
    for index in sample:
        index = int(index)
        if len(run.exposures(index)) < 2:
            continue
        try:
            estimates.append(estimate_noise(run.frames(index), run.exposures(index), run.black_level(index)[0],
                                            white_level=int(run.white_level(index)[0])))  # fmt: skip
        except HDRError as exc:
            log.info("position %d: %s", index, exc)
    if not estimates:
        if mode == "estimated":
            raise ProcessingError(f"{run.path}: the noise model cannot be estimated from these brackets")
        log.warning("%s: noise model from the rig: the brackets did not allow an estimate", run.path)
        return from_rig
    gain = float(np.median([e.gain_e_per_dn for e in estimates]))
    read = float(np.median([e.read_noise_dn for e in estimates]))
    return NoiseModel(gain, read, source="estimated")


def process_run(run_path, out_dir=None, *, steps=("hdr",), method: str = "optimal", noise: str = "auto",
                progress: Callable[[int, int], None] | None = None) -> ProcessReport:  # fmt: skip
    """Process one run file; results go beside it, or into ``out_dir``."""
    from acquisition import __version__

    unknown = [s for s in steps if s not in STEPS]
    if unknown:
        raise ProcessingError(f"--steps: unknown step {unknown[0]!r} (known: {', '.join(STEPS)})")
    run_path = Path(run_path)
    try:
        run = RunFile.open(run_path)
    except RunFileError as exc:
        raise ProcessingError(str(exc)) from None
    with run:
        positions = run.completed_positions()
        if positions.size == 0:
            raise ProcessingError(f"{run_path}: the run has no complete position (no frames to process)")
        out = Path(out_dir) if out_dir is not None else run_path.parent
        out.mkdir(parents=True, exist_ok=True)
        images = out / f"{run_path.stem}.hdr"
        images.mkdir(exist_ok=True)
        model = choose_noise(run, positions, noise)
        cfa = run.cfa_pattern(int(positions[0]))[0]
        results_file = results_path_for(run_path, out)
        report = ProcessReport(run_path, results_file, int(positions.size), model, {"exr": [], "png": []})
        with ResultsWriter.create(results_file, run_id=run.header.run_id, run_file=str(run_path),
                                  n_positions=run.n_positions, frame_shape=run.frame_shape,
                                  software_version=__version__,
                                  hdr=HDRInfo(method, model, rig_noise(run), cfa)) as writer:  # fmt: skip
            for done, index in enumerate(positions, start=1):
                index = int(index)
                try:
                    merged = merge_raw(run.frames(index), run.exposures(index), run.black_level(index)[0],
                                       int(run.white_level(index)[0]), model, method=method)  # fmt: skip
                except HDRError as exc:
                    raise ProcessingError(f"{run_path}: position {index}: {exc}") from None
                writer.write_hdr(index, merged)
                report.saturated_pixels += int(merged.saturated.sum())
                rgb = superpixels(np.where(np.isfinite(merged.radiance), merged.radiance, 0.0), cfa)
                report.outputs["exr"].append(write_exr(images / f"position-{index:03d}.exr", rgb))
                report.outputs["png"].append(write_png(images / f"position-{index:03d}.png", rgb))
                if progress:
                    progress(done, int(positions.size))
        if report.saturated_pixels:
            log.warning("%s: %d pixel samples saturated even in the shortest exposure (flagged in the results)",
                        run_path, report.saturated_pixels)  # fmt: skip
    if math.isnan(model.gain_e_per_dn):  # pragma: no cover - estimate_noise never returns NaN
        raise ProcessingError(f"{run_path}: invalid noise model")
    return report

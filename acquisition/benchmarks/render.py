"""``mirrorgonio bench render``: the simulated camera's rendering of one full frame, timed.

The mirror-ball renderer (:class:`sim_devices.optics.MirrorBallRenderer`: many rays per
pixel, the truth light, diffraction where the rig asks for it) at one schedule position,
next to a trace of one chief ray per pixel through the same optics, which sets the scale of
what a ray costs.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from drivers.contracts.rig import load_rig
from sim_devices.lights import load_truth
from sim_devices.optics import LightPlane, MirrorBallRenderer, trace

#: The rendering of one frame should take no longer (seconds).
TARGET_S = 10.0


def bench_render(rig_path: str | Path | None = None, repeat: int = 3, position: int = 33) -> dict:
    """Render one full frame ``repeat`` times, and trace one chief ray per pixel as often.

    Parameters
    ----------
    rig_path : path, optional
        The rig (default: the default rig).
    repeat : int
        Timed repetitions; the medians are reported.
    position : int
        The schedule position rendered (clipped to the schedule).

    Returns
    -------
    dict
        The JSON ``mirrorgonio bench render`` prints: the medians, the rays per second and
        whether the rendering meets :data:`TARGET_S`.
    """
    rig_model = load_rig(rig_path)
    truth = load_truth(rig_model.simulation.truth)
    poses = rig_model.light_poses()
    pose = poses[min(max(position, 0), len(poses) - 1)]
    renderer = MirrorBallRenderer(rig_model, truth, diffraction=rig_model.simulation.diffraction)
    cam = renderer.camera
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    cols, rows = cols.ravel().astype(float), rows.ravel().astype(float)
    zero = np.zeros_like(cols)
    plane = LightPlane.at(rig_model, pose)

    render_times, chief_times, stats = [], [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        trace(cam, renderer.mirror, plane, cols, rows, zero, zero)
        chief_times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        stats = renderer.render(pose).stats
        render_times.append(time.perf_counter() - t0)
    render_s, chief_s = statistics.median(render_times), statistics.median(chief_times)
    assert stats is not None  # repeat >= 1: median() refuses no times
    return {
        "benchmark": "render",
        "width": cam.width,
        "height": cam.height,
        "truth": truth.name,
        "diffraction": rig_model.simulation.diffraction,
        "repeat": repeat,
        "render_s_median": round(render_s, 4),
        "render_s_all": [round(t, 4) for t in render_times],
        "chief_ray_trace_s_median": round(chief_s, 4),
        "render_over_chief_trace": round(render_s / chief_s, 2),
        "rays_traced_per_frame": stats.rays_traced,
        "rays_per_s": round(stats.rays_traced / render_s),
        "target_s": TARGET_S,
        "meets_target": render_s <= TARGET_S,
    }

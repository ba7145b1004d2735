"""The point spread refined from the sweep: a correction to every channel's kernel, shared by the
positions, estimated with the sources' intensities where the lab has not measured its pinhole.

A pinhole's edge is never a perfect circle. A rough edge (2 µm RMS over 5 µm along it, for
example) scatters a speckled halo about 1e-4 of the peak out to 60-100 px: on the demo rig the
smooth circle's Fresnel templates leave 7 σ² per pixel there, where they leave 1.1 with a
smooth hole. The halo is one pattern for every position (the Fresnel number barely changes over
the sweep), and every position shows it under its own, known mixture of sources. So it can be
taken from the data: the template of a source is its sharp image ``G`` convolved with the
channel's kernel ``K + ΔK``, ``K`` the Fresnel pattern of the described hole and ``ΔK`` the
correction, linear in ``ΔK`` once the intensities are known. The estimate alternates the two
(the intensities per position and channel as the layout fit solves them, ``ΔK`` by LSQR over
every training position; Paige & Saunders 1982), with ``ΔK`` on a grid coarser than the pixels
(bilinear, ``step_px``): the speckle is about λ z₂ / 2a ≈ 11 px across, so the coarse grid loses
nothing the data hold and keeps far fewer unknowns than pixels.

What the data support is judged on positions the estimate did not see: the correction is kept
where the templates' χ² on those falls by ``min_gain`` of its value. A smooth hole's templates
already explain the data to the noise (χ²/pixel ≈ 1.1); the correction is then not estimated at
all, and the processing is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.signal import fftconvolve
from scipy.sparse.linalg import LinearOperator, lsqr
from threadpoolctl import threadpool_limits

from processing.unmixing.kernels import PointSpreadCorrection
from processing.unmixing.measured import MeasuredKernels
from processing.unmixing.problem import LayoutData, LayoutProblem
from processing.unmixing.sources import Source
from processing.unmixing.templates import TemplateBuilder
from processing.unmixing.unmix import nnls_via_cholesky

#: χ² per pixel of the described templates at the training positions above which the point
#: spread is refined (``auto``): 1.1 with a smooth hole on the demo rig, 7.3 with a rough edge.
NEEDED_CHI2_PER_PIXEL = 1.5

#: The fall of the held-out positions' χ² a correction must bring to be kept (``auto``).
MIN_GAIN = 0.2

#: A point's sharp image alone: a kernel of one pixel.
_DELTA = np.ones((3, 1, 1))
_DELTA.flags.writeable = False
_SHARP = MeasuredKernels(_DELTA, 1.0, "a point's sharp image", "delta")


@dataclass
class PointSpreadRefinement:
    """What :func:`refine_point_spread` found: ``correction`` (None where it was not kept, and
    ``message`` says why), the templates' χ² per pixel before and after at the training
    positions and at the held-out ones, and the halo's size (``Σ|ΔK|`` per channel, a fraction
    of a point's flux)."""

    correction: PointSpreadCorrection | None
    needed: bool
    message: str
    chi2_per_pixel_before: float = float("nan")
    chi2_per_pixel_after: float = float("nan")
    held_out_before: float = float("nan")
    held_out_after: float = float("nan")
    halo: tuple[float, float, float] | None = None
    reach_px: int = 0

    def record(self) -> dict[str, Any]:
        """The provenance's and the quality check's record of it."""
        out: dict[str, Any] = {"refined": self.correction is not None, "needed": self.needed, "message": self.message}
        figures = {
            "chi2_per_pixel_before": self.chi2_per_pixel_before,
            "chi2_per_pixel_after": self.chi2_per_pixel_after,
            "held_out_chi2_per_pixel_before": self.held_out_before,
            "held_out_chi2_per_pixel_after": self.held_out_after,
        }
        out |= {k: round(v, 4) for k, v in figures.items() if np.isfinite(v)}
        if self.halo is not None:
            out["halo_abs_sum"] = [round(v, 5) for v in self.halo]
            out["reach_px"] = self.reach_px
        return out


def refine_point_spread(
    train: list[LayoutData],
    held_out: list[LayoutData],
    builder: TemplateBuilder,
    cfa_pattern: str,
    sources: list[Source],
    *,
    force: bool = False,
    reach_px: int = 100,
    step_px: int = 4,
    iterations: int = 2,
    min_gain: float = MIN_GAIN,
    margin_px: int = 48,
    inset_px: int = 8,
) -> PointSpreadRefinement:
    """The correction ``ΔK`` to the builder's kernels that explains ``train`` best with the
    ``sources`` where they are, kept if it lowers the χ² of ``held_out`` by ``min_gain``
    (``force``: estimated whatever the χ², kept if it lowers it at all)."""
    if builder.measured is not None:
        return PointSpreadRefinement(None, False, "the camera's measured point spread is used")
    if builder.pupil is None:
        return PointSpreadRefinement(None, False, "refined only on the Fresnel templates (camera.point_spread)")
    with threadpool_limits(limits=1, user_api="blas"):
        problem = LayoutProblem([*train, *held_out], builder, cfa_pattern, sources, margin_px, inset_px)
        windows = _Windows(problem, sources, len(train), reach_px, step_px)
        if not windows.train or not windows.held:
            return PointSpreadRefinement(None, False, "too few positions with a window where every template is whole")
        before, held_before = windows.chi2(None, True), windows.chi2(None, False)
        if before < NEEDED_CHI2_PER_PIXEL and not force:
            message = f"not needed: the templates explain the data (χ²/pixel {before:.3g})"
            return PointSpreadRefinement(
                None, False, message, chi2_per_pixel_before=before, held_out_before=held_before
            )
        correction = windows.kernel_step()  # at the described templates' intensities, solved above
        for _ in range(iterations - 1):
            windows.chi2(correction, True)  # the intensities with the kernel as it stands
            correction = windows.kernel_step()
        after, held_after = windows.chi2(correction, True), windows.chi2(correction, False)
        gain = 1.0 - held_after / held_before
        kept = gain > (0.0 if force else min_gain)
        halo = tuple(float(v) for v in np.abs(correction).sum(axis=(1, 2)))
        message = (
            f"{'kept' if kept else 'not kept'}: the held-out positions' χ²/pixel "
            f"{held_before:.3g} → {held_after:.3g} ({100 * gain:+.0f} %)"
        )
        return PointSpreadRefinement(
            PointSpreadCorrection.of(correction) if kept else None,
            True,
            message,
            chi2_per_pixel_after=after,
            held_out_after=held_after,
            chi2_per_pixel_before=before,
            held_out_before=held_before,
            halo=(halo[0], halo[1], halo[2]),
            reach_px=reach_px,
        )


@dataclass
class _Window:
    """One position's window: each source's described template and sharp image (S, 3, h, w)
    and (S, 3, h + 2R, w + 2R), the fitted pixels, their weights and weighted data per channel,
    and the intensities last solved for (per channel, S)."""

    described: np.ndarray
    sharp: np.ndarray
    picks: list[np.ndarray]
    weights: list[np.ndarray]
    targets: list[np.ndarray]
    train: bool
    x: list[np.ndarray] = field(default_factory=list)


class _Windows:
    """The layout problem's windows as the estimate uses them: each source's template (the
    described kernels, as far out as the correction reaches) and its sharp image on the window
    grown by the reach, per channel, at the fitted pixels."""

    def __init__(self, problem: LayoutProblem, sources: list[Source], n_train: int, reach: int, step: int):
        self.reach = reach
        smooth = replace(problem.builder, airy_margin_px=max(problem.builder.airy_margin_px, reach))
        sharp = replace(problem.builder, measured=_SHARP, pupil=None)
        self.items: list[_Window] = []
        for index, (pose, window, _, picks, weights, targets) in zip(problem.window_data, problem.windows, strict=True):
            top, bottom, left, right = window
            shape = (bottom - top, right - left)
            described = np.stack([_dense(smooth, s, pose, top, left, shape) for s in sources])
            grown = (shape[0] + 2 * reach, shape[1] + 2 * reach)
            images = np.stack([_dense(sharp, s, pose, top - reach, left - reach, grown) for s in sources])
            self.items.append(_Window(described, images, picks, weights, targets, index < n_train))
        self.train = [item for item in self.items if item.train]
        self.held = [item for item in self.items if not item.train]
        self.pixels = {
            flag: sum(int(np.count_nonzero(p)) for item in self.items if item.train == flag for p in item.picks)
            for flag in (True, False)
        }
        nodes = np.arange(-reach, reach + 1e-9, step)
        self.spread = np.clip(1.0 - np.abs(np.arange(-reach, reach + 1)[:, None] - nodes[None, :]) / step, 0.0, None)

    def chi2(self, correction: np.ndarray | None, train: bool) -> float:
        """χ² per pixel of the windows (training or held out) with the intensities solved for
        at each (NNLS per channel), which are kept on each window for :meth:`kernel_step`."""
        total = 0.0
        for item in self.train if train else self.held:
            item.x = []
            for c in range(3):
                columns = item.described[:, c]
                if correction is not None:
                    columns = columns + np.stack(
                        [fftconvolve(image, correction[c], mode="valid") for image in item.sharp[:, c]]
                    )
                a = columns[:, item.picks[c]].T * item.weights[c][:, None]
                gram = a.T @ a
                ridge = 1e-12 * max(float(np.trace(gram)), 1e-300) * np.eye(gram.shape[0])
                x = nnls_via_cholesky(a, item.targets[c], gram + ridge, maxiter=100 * gram.shape[0])
                item.x.append(x)
                residual = a @ x - item.targets[c]
                total += float(residual @ residual)
        return total / max(1, self.pixels[train])

    def kernel_step(self) -> np.ndarray:
        """Each channel's ``ΔK`` on the reach's grid, by LSQR on the coarse nodes, at the
        training windows' intensities."""
        spread, nodes = self.spread, self.spread.shape[1]
        out = []
        for c in range(3):
            scenes = [np.tensordot(item.x[c], item.sharp[:, c], axes=1) for item in self.train]
            rhs = [
                item.targets[c] - np.tensordot(item.x[c], item.described[:, c], axes=1)[item.picks[c]] * item.weights[c]
                for item in self.train
            ]

            def forward(coarse: np.ndarray, c: int = c, scenes: list[np.ndarray] = scenes) -> np.ndarray:
                kernel = spread @ coarse.reshape(nodes, nodes) @ spread.T
                return np.concatenate(
                    [
                        fftconvolve(scene, kernel, mode="valid")[item.picks[c]] * item.weights[c]
                        for scene, item in zip(scenes, self.train, strict=True)
                    ]
                )

            def adjoint(residual: np.ndarray, c: int = c, scenes: list[np.ndarray] = scenes) -> np.ndarray:
                total, start = np.zeros((spread.shape[0],) * 2), 0
                for scene, item in zip(scenes, self.train, strict=True):
                    picks = item.picks[c]
                    image = np.zeros(picks.shape)
                    n = int(np.count_nonzero(picks))
                    image[picks] = residual[start : start + n] * item.weights[c]
                    start += n
                    total += fftconvolve(scene, image[::-1, ::-1], mode="valid")[::-1, ::-1]
                return (spread.T @ total @ spread).ravel()

            size = sum(r.size for r in rhs)
            operator = LinearOperator((size, nodes * nodes), matvec=forward, rmatvec=adjoint)
            coarse = lsqr(operator, np.concatenate(rhs), iter_lim=50)[0]
            out.append(spread @ coarse.reshape(nodes, nodes) @ spread.T)
        return np.stack(out)


def _dense(
    builder: TemplateBuilder, source: Source, pose: Any, top: int, left: int, shape: tuple[int, int]
) -> np.ndarray:
    """The source's template (3, h, w) on the grid whose top-left pixel is (top, left)."""
    out = np.zeros((3, *shape))
    template = builder.build(source, pose)
    if template is None:
        return out
    r0, c0 = template.row0 - top, template.col0 - left
    h, w = template.image.shape[1:]
    a0, b0, a1, b1 = max(r0, 0), max(c0, 0), min(r0 + h, shape[0]), min(c0 + w, shape[1])
    if a1 > a0 and b1 > b0:
        out[:, a0:a1, b0:b1] = template.image[:, a0 - r0 : a1 - r0, b0 - c0 : b1 - c0]
    return out

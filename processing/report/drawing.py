"""Figures drawn with matplotlib's Agg canvas directly, laid out by hand, encoded as PNG."""

from __future__ import annotations

import logging
import math
from typing import Any, Literal, cast

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from numpy.typing import ArrayLike

from processing.images import encode_png

log = logging.getLogger("mirrorgonio.processing")


DPI = 100


COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22")


def new_figure(
    width: float, height: float, layout: Literal["constrained", "compressed", "tight"] | None = "constrained"
) -> Figure:
    fig = Figure(figsize=(width, height), dpi=DPI, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def axes_in(fig: Figure, left: float, bottom: float, right: float, top: float, **kwargs: Any) -> Axes:
    """An axes placed by its margins in inches. The report's figures are laid out by hand: a layout
    engine measures every label at draw time (and ``savefig`` draws twice for it), which cost more
    than the drawing itself; the margins hold the labels at the fonts' fixed sizes."""
    w, h = fig.get_size_inches()
    return fig.add_axes((left / w, bottom / h, 1.0 - (left + right) / w, 1.0 - (bottom + top) / h), **kwargs)


def settle_axes(ax: Axes, *, xlabel_pad: float | None = 0.3, ylabel_pad: float | None = 0.5) -> None:
    """Fix what matplotlib would otherwise work out at draw time, once the axes holds its data: the
    ticks, to those in view (its locators also make and measure a tick past each end, never drawn),
    and the axis labels' place, ``xlabel_pad`` inches below and ``ylabel_pad`` inches left of the
    axes (instead of measuring every tick label)."""
    for axis, limits in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
        lo, hi = min(limits), max(limits)
        slack = 1e-9 * (hi - lo)
        axis.set_ticks([t for t in axis.get_major_locator()() if lo - slack <= t <= hi + slack])
    figure = cast(Figure, ax.get_figure())  # the report's axes sit on a Figure (never a SubFigure)
    box, (w, h) = ax.get_position(), figure.get_size_inches()
    if xlabel_pad is not None:
        ax.xaxis.set_label_coords(0.5, -xlabel_pad / (box.height * h))
    if ylabel_pad is not None:
        ax.yaxis.set_label_coords(-ylabel_pad / (box.width * w), 0.5)


def figure_pixels(fig: Figure) -> np.ndarray:
    """The figure drawn by Agg, as an (h, w, 3) RGB array (the figures are opaque: no alpha to keep)."""
    fig.canvas.draw()
    canvas = cast(FigureCanvasAgg, fig.canvas)  # new_figure gives every figure an Agg canvas
    return np.array(np.asarray(canvas.buffer_rgba())[..., :3])


def encode_rgb_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB array, deflated by ISA-L (:func:`processing.images.encode_png`, level 2).
    On a 900x600 figure: 0.5 ms for 76 kB, where Pillow's zlib at level 3 takes 10 ms for 71 kB."""

    return encode_png(np.ascontiguousarray(rgb), level=2)


def figure_png(fig: Figure) -> bytes:
    return encode_rgb_png(figure_pixels(fig))


def add_line(ax: Axes, x: ArrayLike, y: ArrayLike, **kwargs: Any) -> Line2D:
    """A line added to ``ax`` without ``plot``'s argument parsing nor the data limits' update (the
    callers set their limits)."""
    return cast(Line2D, ax.add_artist(Line2D(x, y, **kwargs)))  # add_artist returns the artist it adds


def grown_runs(mask: np.ndarray) -> np.ndarray:
    """``mask`` grown by one sample each way, so that a solid and a dashed curve meet."""
    grown = mask.copy()
    grown[1:] |= mask[:-1]
    grown[:-1] |= mask[1:]
    return grown


def panel_grid(rows_cols: int) -> tuple[int, int]:
    cols = min(rows_cols, 3)
    return math.ceil(rows_cols / cols), cols


def warm_up_drawing() -> None:
    """Draw and encode a tiny figure with text: matplotlib's fonts and Agg loaded, so that the
    first section a fresh worker draws costs what the next ones do."""
    fig = new_figure(2.0, 1.0, layout=None)
    ax = fig.add_subplot()
    ax.errorbar([0, 1], [0, 1], yerr=[0.1, 0.1], fmt="o", label="σ χ²ᵣ")
    ax.set_xlabel("θ [°]", fontsize=8)
    ax.set_title("source", fontweight="bold")
    ax.legend(fontsize=8, frameon=False)
    figure_png(fig)

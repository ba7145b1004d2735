"""The run's report: one self-contained HTML page that shows the measured light.

:func:`write_report` turns a :class:`~processing.lightmodel.LightModel` (and, when they are
at hand, the run file, the per-position samples and the pipeline's
:class:`~processing.pipeline.ProcessReport`) into a single HTML file whose figures are
embedded as base64 PNG: no external asset, so the file can be mailed or archived alone.
A person should understand the light from the figures without reading the numbers:

1. the header: run, rig, date, units, the estimator and why it was chosen, the spatial
   resolution the camera allows on the light plane, the noise model;
2. per source, a half-polar plot of its radiant intensity ``I_s(θ)`` (the reference
   paper's Figs. 6 and 8): samples, the fit (solid where the samples cover θ, dashed where
   it extrapolates), the chief-ray cell sums for comparison and, for a simulated run, the
   truth;
3. the sources on the light plane with the footprint of one pixel drawn to scale;
4. the θ each source was sampled at, position by position;
5. how the ball widens the angles (the paper's Fig. 5): outgoing θ against the deflection
   the ball gives each chief ray, at the middle position;
6. the residuals of every fit, its reduced χ² and its parameters with uncertainties;
7. the calibration check (measured against described ball centre, and what 1 mm of error
   in the ball's position costs in angle);
8. a strip of the HDR previews over the sweep.

The polar plots show θ *signed by side*: the sweep carries the light past the ball, so its
samples leave on both sides of the light's axis; a sample whose azimuth lies within 90° of
the sweep's main azimuth ``φ_s`` is drawn at +θ, the others at −θ.

The figures are drawn with matplotlib's Agg canvas directly (no pyplot, no global
backend), laid out by hand (no layout engine), the half discs on plain axes (no polar
projection); one worker thread encodes their PNGs and does the calibration's sensitivity
and the previews while the next figure is drawn: what the report costs is mostly
matplotlib's text rendering. Given the processing's Dask cluster (``compute=``), its
workers draw the five sections that need only the model, the samples and the chief rays,
each in its own process, and the page is the same (:data:`_REMOTE_SECTIONS`). Each section
that cannot be drawn (missing inputs) says why instead; a section that fails is reported in
the page and logged, and never stops the processing.

The truth, for simulated runs, is a callable ``truth(source, theta) -> intensity`` passed by
the caller (the processing never imports the simulator). It is called with the source's
index in ``model.sources`` first and, if that raises ``LookupError`` or ``TypeError``, with
its name; ``None`` means no truth for that source.
"""

from __future__ import annotations

import base64
import gc
import html
import logging
import math
import re
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.container import ErrorbarContainer
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Polygon
from matplotlib.ticker import MaxNLocator

from processing.lightmodel import LightModel, SourceModel, describe_fitted

__all__ = [
    "angles_figure",
    "coverage_figure",
    "layout_figure",
    "polar_figure",
    "reflectance_profiles_figure",
    "reflectance_section",
    "residuals_figure",
    "write_reflectance_report",
    "write_report",
]

log = logging.getLogger("mirrorgonio.processing")
_DPI = 100
_PREVIEWS = 6
_PREVIEW_WIDTH = 320
_PREVIEW_CROP = 200
_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
NO_CALIBRATION = "no calibration image in this run"
_SECTIONS = (
    "The light source, source by source",
    "The sources on the light plane",
    "Which θ each source was sampled at",
    "How the ball widens the angles",
    "How well the fits describe the samples",
    "Calibration check: the ball's position",
    "HDR frames over the sweep",
)


# --- the data the figures share ------------------------------------------------------------------
@dataclass
class _SourceData:
    """One source's samples as plain arrays (NaN where a column is missing)."""

    theta: np.ndarray
    phi: np.ndarray
    intensity: np.ndarray
    sigma: np.ndarray
    position: np.ndarray
    cell_sum: np.ndarray | None


@dataclass
class _Geometry:
    """The middle position's chief-ray trace, when the run is at hand."""

    index: int
    pose: object
    geometry: object
    rays: object | None = None
    pixel_polygon: np.ndarray | None = None  # (4, 2) metres on the light plane
    pixel_at: tuple[float, float] | None = None


@dataclass
class _Context:
    model: LightModel
    data: list[_SourceData]
    azimuth: float  # the sweep's main azimuth φ_s, radians in (−π/2, π/2]
    truth: Callable | None
    resolution_m: float
    colours: list[str] = field(default_factory=list)
    geometry: _Geometry | None = None
    geometry_note: str = ""
    encoder: _Encoder | None = None


def _column(table: dict, key: str) -> np.ndarray | None:
    if key not in table or table[key] is None:
        return None
    return np.asarray([np.nan if v is None else v for v in table[key]], dtype=float)


def _source_data(model: LightModel, samples=None) -> list[_SourceData]:
    """Every source's samples: the model's tables (what was fitted), else the pipeline's
    :class:`SourceSamples` columns."""
    out = []
    for k, source in enumerate(model.sources):
        table = source.samples or {}
        theta = _column(table, "theta")
        if theta is None and samples is not None:
            ok = np.isfinite(samples.intensity[:, k]) & np.isfinite(samples.theta[:, k])
            cell = np.asarray(samples.cell_sum[:, k], dtype=float)[ok]
            out.append(
                _SourceData(
                    np.asarray(samples.theta[:, k])[ok],
                    np.asarray(samples.phi[:, k])[ok],
                    np.asarray(samples.intensity[:, k])[ok],
                    np.asarray(samples.sigma[:, k])[ok],
                    np.asarray(samples.positions)[ok].astype(float),
                    cell,
                )
            )
            continue
        if theta is None:
            empty = np.zeros(0)
            out.append(_SourceData(empty, empty, empty, empty, empty, None))
            continue
        n = len(theta)

        def col(key, default=np.nan, table=table, n=n):
            value = _column(table, key)
            return value if value is not None and len(value) == n else np.full(n, default)

        position = _column(table, "position")
        cell = _column(table, "cell_sum_intensity")
        out.append(
            _SourceData(
                theta,
                col("phi", 0.0),
                col("intensity"),
                col("sigma"),
                position if position is not None and len(position) == n else np.arange(n, dtype=float),
                cell if cell is not None and len(cell) == n else None,
            )
        )
    return out


def _sweep_azimuth(data: list[_SourceData]) -> float:
    """The samples' main azimuth, modulo π (weighted by sin θ: the axis carries no azimuth)."""
    s = c = 0.0
    for d in data:
        ok = np.isfinite(d.theta) & np.isfinite(d.phi)
        w = np.sin(d.theta[ok])
        s += float(np.sum(w * np.sin(2.0 * d.phi[ok])))
        c += float(np.sum(w * np.cos(2.0 * d.phi[ok])))
    if s == 0.0 and c == 0.0:
        return 0.0
    return 0.5 * math.atan2(s, c)  # in (−π/2, π/2]


def _deg(angle: float) -> str:
    """An angle in whole degrees (an int: never "-0")."""
    return f"{round(math.degrees(angle)):d}°"


def _signed(theta, phi, azimuth: float) -> np.ndarray:
    """θ with the sign of its side: + within 90° of the sweep's azimuth, − opposite."""
    theta = np.asarray(theta, dtype=float)
    return np.where(np.cos(np.asarray(phi, dtype=float) - azimuth) >= 0.0, theta, -theta)


def _truth_values(truth, k: int, name: str, theta: np.ndarray) -> np.ndarray | None:
    if truth is None:
        return None
    for key in (k, name):
        try:
            value = truth(key, theta)
        except (LookupError, TypeError):
            continue
        if value is None:
            return None
        return np.broadcast_to(np.asarray(value, dtype=float), np.shape(theta)).copy()
    return None


def _truth_error(source: SourceModel, truth, k: int) -> float | None:
    """RMS(I_fit − I_true) / max(I_true) over the θ the samples cover (``measurement.md``)."""
    lo, hi = source.fit.theta_range
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return None
    grid = np.linspace(lo, hi, 200)
    true = _truth_values(truth, k, source.name, grid)
    if true is None or not np.all(np.isfinite(true)) or np.max(true) <= 0:
        return None
    return math.sqrt(float(np.mean((source.fit(grid) - true) ** 2))) / float(np.max(true))


def _context(model: LightModel, *, samples=None, truth=None, resolution_m=float("nan")) -> _Context:
    data = _source_data(model, samples)
    colours = [_COLOURS[k % len(_COLOURS)] for k in range(len(model.sources))]
    return _Context(model, data, _sweep_azimuth(data), truth, resolution_m, colours)


# --- figures ----------------------------------------------------------------------------------------
def _new_figure(width: float, height: float, layout: str | None = "constrained") -> Figure:
    fig = Figure(figsize=(width, height), dpi=_DPI, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _axes_in(fig: Figure, left: float, bottom: float, right: float, top: float, **kwargs):
    """An axes placed by its margins in inches. The report's figures are laid out by hand: a layout
    engine measures every label at draw time (and ``savefig`` draws twice for it), which cost more
    than the drawing itself; the margins hold the labels at the fonts' fixed sizes."""
    w, h = fig.get_size_inches()
    return fig.add_axes((left / w, bottom / h, 1.0 - (left + right) / w, 1.0 - (bottom + top) / h), **kwargs)


def _settle(ax, *, xlabel_pad: float | None = 0.3, ylabel_pad: float | None = 0.5) -> None:
    """Fix what matplotlib would otherwise work out at draw time, once the axes holds its data: the
    ticks, to those in view (its locators also make and measure a tick past each end, never drawn),
    and the axis labels' place, ``xlabel_pad`` inches below and ``ylabel_pad`` inches left of the
    axes (instead of measuring every tick label)."""
    for axis, limits in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
        lo, hi = min(limits), max(limits)
        slack = 1e-9 * (hi - lo)
        axis.set_ticks([t for t in axis.get_major_locator()() if lo - slack <= t <= hi + slack])
    box, (w, h) = ax.get_position(), ax.get_figure().get_size_inches()
    if xlabel_pad is not None:
        ax.xaxis.set_label_coords(0.5, -xlabel_pad / (box.height * h))
    if ylabel_pad is not None:
        ax.yaxis.set_label_coords(-ylabel_pad / (box.width * w), 0.5)


def _pixels(fig: Figure) -> np.ndarray:
    """The figure drawn by Agg, as an (h, w, 3) RGB array (the figures are opaque: no alpha to keep)."""
    fig.canvas.draw()
    return np.array(np.asarray(fig.canvas.buffer_rgba())[..., :3])


def _encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB array, deflated by ISA-L (:func:`processing.images.encode_png`, level 2).
    On a 900x600 figure: 0.5 ms for 76 kB, where Pillow's zlib at level 3 took 10 ms for 71 kB."""
    from processing.images import encode_png

    return encode_png(np.ascontiguousarray(rgb), level=2)


def _png(fig: Figure) -> bytes:
    return _encode_png(_pixels(fig))


class _Encoder:
    """Encodes the figures' PNGs on a worker thread (the deflate releases the GIL) while the next
    figure is drawn: :meth:`figure` draws and returns the ``<figure>`` with a placeholder that
    :meth:`fill` replaces by the embedded image."""

    def __init__(self, pool):
        self.pool = pool
        self.pending: dict[str, tuple[object, str]] = {}

    def figure(self, fig: Figure, alt: str, caption: str) -> str:
        token = f"\x00figure-{len(self.pending)}\x00"
        self.pending[token] = (self.pool.submit(_encode_png, _pixels(fig)), alt)
        return f"<figure>{token}<figcaption>{caption}</figcaption></figure>"

    def fill(self, text: str) -> str:
        for token, (future, alt) in self.pending.items():
            if token in text:
                try:
                    image = _img(future.result(), alt)
                except Exception as exc:  # noqa: BLE001 - a figure never stops the processing
                    log.warning("report: %s: %s", alt, exc, exc_info=True)
                    image = _note(f"this figure could not be encoded: {type(exc).__name__}: {exc}")
                text = text.replace(token, image)
        return text


def _line(ax, x, y, **kwargs) -> Line2D:
    """A line added to ``ax`` without ``plot``'s argument parsing nor the data limits' update (the
    callers set their limits)."""
    return ax.add_artist(Line2D(x, y, **kwargs))


def _runs(mask: np.ndarray) -> np.ndarray:
    """``mask`` grown by one sample each way, so that a solid and a dashed curve meet."""
    grown = mask.copy()
    grown[1:] |= mask[:-1]
    grown[:-1] |= mask[1:]
    return grown


def _grid(rows_cols: int) -> tuple[int, int]:
    cols = min(rows_cols, 3)
    return math.ceil(rows_cols / cols), cols


def _fit_curve(source: SourceModel, signed_theta: np.ndarray, azimuth: float):
    theta = np.abs(signed_theta)
    phi = np.where(signed_theta >= 0.0, azimuth, azimuth + math.pi)
    values, extrapolated = source.fit.evaluate(theta, phi)
    values = np.where(theta <= 0.5 * math.pi, np.maximum(values, 0.0), 0.0)
    return values, extrapolated


def _polar_frame(ax, rmax: float, clip) -> None:
    """The half disc's grid, drawn by hand: spokes every 30°, arcs at round radii, their labels."""
    arc = np.radians(np.linspace(-90.0, 90.0, 181))
    ticks = MaxNLocator(nbins=6, steps=[1, 2, 2.5, 5, 10]).tick_values(0.0, rmax)
    ticks = ticks[(ticks >= 0.0) & (ticks < rmax * (1.0 - 1e-9))]
    segments = [np.column_stack([t / rmax * np.sin(arc), t / rmax * np.cos(arc)]) for t in ticks if t > 0.0]
    spokes = np.radians(np.arange(-90, 91, 30))
    segments += [np.array([[0.0, 0.0], [math.sin(a), math.cos(a)]]) for a in spokes]
    ax.add_artist(LineCollection(segments, colors="#b0b0b0", linewidths=0.8, zorder=1.5))
    ax.add_artist(clip)  # the rim and the baseline, as a polar plot's spines
    for a in spokes:  # θ labels outside the rim, 0° up
        s, c = math.sin(a), math.cos(a)
        ax.text(
            1.06 * s,
            1.06 * c,
            f"{round(math.degrees(a))}°",
            fontsize=8,
            ha="center" if abs(s) < 0.3 else ("left" if s > 0 else "right"),
            va="bottom" if c > 0.3 else "center",
        )
    if ticks.size > 1:  # the radial scale under the baseline, left of the axis, with the decimals its step needs
        step = float(ticks[1] - ticks[0])
        decimals = max(0, -math.floor(math.log10(step)))
        decimals += not math.isclose(step * 10**decimals, round(step * 10**decimals), rel_tol=1e-6)
        for t in ticks:
            ax.text(-t / rmax, -0.03, f"{t:.{decimals}f}", fontsize=7, ha="center", va="top")


def _polar_panel(ax, ctx: _Context, k: int) -> list:
    """One source's half-polar plot, drawn on a Cartesian axes whose unit is the radial scale's top
    (θ from the vertical, signed by side: x = r sin θ, y = r cos θ); returns the legend handles it drew."""
    source, d, colour = ctx.model.sources[k], ctx.data[k], ctx.colours[k]
    grid = np.radians(np.linspace(-90.0, 90.0, 721))
    fit, extrapolated = _fit_curve(source, grid, ctx.azimuth)
    signed = _signed(d.theta, d.phi, ctx.azimuth)
    true = _truth_values(ctx.truth, k, source.name, np.abs(grid))
    sigma = np.where(np.isfinite(d.sigma), d.sigma, 0.0)
    # the radial scale: what the data, the covered fit and the truth reach (an extrapolation may run away)
    reach = [d.intensity + sigma, fit[~extrapolated] if np.any(~extrapolated) else fit[np.abs(grid) < 1.4]]
    reach += [a for a in (d.cell_sum, true) if a is not None]
    finite = np.concatenate([np.ravel(a)[np.isfinite(np.ravel(a))] for a in reach])
    rmax = 1.12 * max(float(finite.max()) if finite.size else 0.0, 1e-30)
    sin_grid, cos_grid = np.sin(grid), np.cos(grid)

    def xy(theta, r):
        r = np.asarray(r, dtype=float) / rmax
        return r * np.sin(theta), r * np.cos(theta)

    rim = np.radians(np.linspace(-90.0, 90.0, 181))
    clip = Polygon(
        np.column_stack([np.sin(rim), np.cos(rim)]), closed=True, facecolor="none", edgecolor="k", lw=0.8, zorder=2.5
    )
    _polar_frame(ax, rmax, clip)
    handles, drawn = [], []
    # the θ the samples cover, side by side
    for side in (1.0, -1.0):
        on_side = signed[np.isfinite(signed) & (np.sign(signed) == side)] if signed.size else np.zeros(0)
        if on_side.size:
            span = np.linspace(on_side.min(), on_side.max(), 50)
            wedge = Polygon(
                np.column_stack([np.r_[0.0, np.sin(span)], np.r_[0.0, np.cos(span)]]),
                closed=True,
                facecolor="0.5",
                alpha=0.10,
                linewidth=0,
            )
            drawn.append(ax.add_artist(wedge))
    shown = np.where(fit <= 1.05 * rmax, fit, np.nan) / rmax
    solid = np.where(~extrapolated, shown, np.nan)
    dashed = np.where(_runs(extrapolated), shown, np.nan)
    handles.append(_line(ax, solid * sin_grid, solid * cos_grid, color=colour, lw=2.0, label="fit (θ covered)"))
    handles.append(
        _line(
            ax,
            dashed * sin_grid,
            dashed * cos_grid,
            color=colour,
            lw=1.4,
            ls="--",
            alpha=0.45,
            label="fit, extrapolated",
        )
    )
    drawn += handles
    if true is not None:
        r = np.where(true <= 1.05 * rmax, true, np.nan) / rmax
        h = _line(ax, r * sin_grid, r * cos_grid, color="k", lw=1.2, ls=(0, (6, 3)), label="truth")
        handles.append(h)
        drawn.append(h)
    if (
        d.cell_sum is not None
        and np.any(np.isfinite(d.cell_sum))
        and not np.allclose(d.cell_sum, d.intensity, equal_nan=True)
    ):
        h = _line(
            ax,
            *xy(signed, d.cell_sum),
            ls="none",
            marker="^",
            ms=4,
            mfc="none",
            mec="0.35",
            mew=0.8,
            label="chief-ray cell sums",
        )
        handles.append(h)
        drawn.append(h)
    if d.intensity.size:
        has_sigma = bool(np.any(np.isfinite(d.sigma) & (d.sigma > 0)))
        bars = ()
        if has_sigma:  # the ±1σ bars run along the radius
            ends = np.stack(
                [
                    np.column_stack(xy(signed, np.maximum(d.intensity - sigma, 0.0))),
                    np.column_stack(xy(signed, d.intensity + sigma)),
                ],
                axis=1,
            )
            bars = (ax.add_artist(LineCollection(ends, colors=colour, linewidths=0.9)),)
            drawn += bars
        line = _line(
            ax,
            *xy(signed, d.intensity),
            ls="none",
            marker="o",
            ms=3.2,
            color=colour,
            mec="k",
            mew=0.4,
            label="samples ± 1σ",
        )
        drawn.append(line)
        handles.append(ErrorbarContainer((line, (), bars), has_xerr=False, has_yerr=has_sigma, label="samples ± 1σ"))
    for artist in drawn:
        artist.set_clip_path(clip)
    return handles


def polar_figure(model: LightModel, *, samples=None, truth=None) -> Figure:
    """Per source, the radiant intensity ``I_s(θ)`` on a half-polar plot (θ from −90° to 90°).

    Dots: the samples with ±1σ bars; solid line: the fit over the θ its samples cover,
    dashed where it extrapolates; open triangles: the chief-ray cell sums of the same
    positions (when the estimator was not the cell sums themselves); broken black line:
    the truth, when ``truth`` is given; grey wedges: the θ the samples cover on each side.

    Each half disc is drawn by hand on a Cartesian axes (matplotlib's polar axes cost
    several times as much to make and draw) whose unit length is the top of its radial
    scale: a sample at signed angle θ and intensity I sits at ``(I sin θ, I cos θ) / I_top``.
    """
    ctx = _context(model, samples=samples, truth=truth)
    return _polar_figure(ctx)


def _polar_figure(ctx: _Context) -> Figure:
    n = len(ctx.model.sources)
    rows, cols = _grid(n)
    cell_w, cell_h, radius = 4.2, 2.6, 1.65  # inches: a cell, and the radius of its half disc
    top_band, legend_band = 0.3, 0.45
    pad_x, pad_bottom, pad_top = 0.45, 0.3, 0.3  # around the half disc, for its labels
    width, height = cell_w * cols, top_band + cell_h * rows + legend_band
    fig = _new_figure(width, height, layout=None)
    handles = {}
    for k in range(n):
        r, c = divmod(k, cols)
        cell_top = height - top_band - r * cell_h
        base = cell_top - 0.58 - radius  # the baseline: the title and the 0° label above the half disc
        centre = (c + 0.5) * cell_w
        ax = fig.add_axes(
            (
                (centre - radius - pad_x) / width,
                (base - pad_bottom) / height,
                2.0 * (radius + pad_x) / width,
                (radius + pad_bottom + pad_top) / height,
            )
        )
        ax.set_axis_off()
        ax.set_xlim(-1.0 - pad_x / radius, 1.0 + pad_x / radius)
        ax.set_ylim(-pad_bottom / radius, 1.0 + pad_top / radius)
        for h in _polar_panel(ax, ctx, k):
            handles.setdefault(h.get_label(), h)
        source = ctx.model.sources[k]
        fig.text(
            centre / width,
            (cell_top - 0.02) / height,
            f"{source.name}  ({source.fit.method}, χ²ᵣ = {source.fit.chi2_reduced:.2g})",
            ha="center",
            va="top",
            fontsize=10,
        )
    order = ["samples ± 1σ", "fit (θ covered)", "fit, extrapolated", "chief-ray cell sums", "truth"]
    shown = [handles[label] for label in order if label in handles]
    fig.legend(
        shown,
        [h.get_label() for h in shown],
        loc="lower center",
        bbox_to_anchor=(0.5, 0.0),
        ncols=len(shown),
        fontsize=9,
        frameon=False,
    )
    fig.text(
        0.5,
        1.0 - 0.08 / height,
        f"radiant intensity I(θ) [{ctx.model.units}] as the radius; θ from the light's axis (up), signed by side",
        ha="center",
        va="top",
        fontsize=9,
        color="0.3",
    )
    return fig


def layout_figure(model: LightModel, *, resolution_m: float = float("nan"), pixel_polygon=None) -> Figure:
    """The sources on the light plane (circles of their radius) and, drawn to scale, the
    footprint of one pixel: the point spread's (diameter ``resolution_m``) and, when known,
    the chief ray's own (``pixel_polygon``, (4, 2) metres)."""
    colours = [_COLOURS[k % len(_COLOURS)] for k in range(len(model.sources))]
    fig = _new_figure(6.4, 6.0, layout=None)
    has_footprint = math.isfinite(resolution_m) and resolution_m > 0
    legend_lines = int(has_footprint) + int(pixel_polygon is not None)
    bottom = 0.5 + 0.2 * legend_lines
    side = 6.0 - bottom - 0.1  # a square axes: the limits below span the same in u and v
    ax = _axes_in(fig, 0.75, bottom, 6.4 - 0.75 - side, 0.1)
    centres = np.array([s.centre_m for s in model.sources], dtype=float) * 1e3
    radii = np.array([s.radius_m for s in model.sources], dtype=float) * 1e3
    spacing = 1.0
    if len(centres) > 1:
        dist = np.hypot(*(centres[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
        spacing = float(np.min(dist[dist > 0])) if np.any(dist > 0) else 1.0
    marker_floor = 0.04 * spacing
    for k, (source, (u, v), r) in enumerate(zip(model.sources, centres, radii, strict=True)):
        ax.add_patch(
            Circle((u, v), max(r, marker_floor), facecolor=colours[k], alpha=0.55, edgecolor=colours[k], lw=1.2)
        )
        ax.plot([u], [v], "+", color="k", ms=6, mew=0.8)
        ax.annotate(
            source.name,
            (u, v),
            xytext=(6, 6),
            textcoords="offset points",
            fontsize=10,
            color=colours[k],
            fontweight="bold",
        )
    centroid = centres.mean(axis=0)
    handles = []
    lo = (centres - radii[:, None]).min(axis=0)
    hi = (centres + radii[:, None]).max(axis=0)
    if has_footprint:
        rad = 0.5 * resolution_m * 1e3
        handles.append(
            ax.add_patch(
                Circle(
                    tuple(centroid),
                    rad,
                    fill=False,
                    ls="--",
                    lw=1.4,
                    edgecolor="0.3",
                    label=f"what one pixel gathers light from: the point spread's footprint ({2 * rad:.1f} mm across)",
                )
            )
        )
        lo = np.minimum(lo, centroid - rad)
        hi = np.maximum(hi, centroid + rad)
    if pixel_polygon is not None:
        # a scale glyph in the lower-left corner, clear of the sources (its shape and size are the pixel's)
        poly = np.asarray(pixel_polygon, dtype=float) * 1e3
        poly = poly - poly.min(axis=0)
        size = poly.max(axis=0)
        corner = lo + 0.02 * max(float(np.max(hi - lo)), 1.0)
        clear = np.all(np.hypot(*(centres - (corner + 0.5 * size)).T) > radii + 0.75 * float(np.hypot(*size)))
        poly = poly + (corner if clear else lo - size - 0.05 * max(float(np.max(hi - lo)), 1.0))
        label = f"one pixel's chief-ray footprint ({size[0]:.2f} × {size[1]:.2f} mm), to scale, lower left"
        handles.append(
            ax.add_patch(
                Polygon(poly, closed=True, facecolor="0.2", edgecolor="k", lw=0.8, alpha=0.8, zorder=3, label=label)
            )
        )
        lo = np.minimum(lo, poly.min(axis=0))
        hi = np.maximum(hi, poly.max(axis=0))
    span = max(float(np.max(hi - lo)), 2.0 * spacing, 1.0)
    mid = 0.5 * (lo + hi)
    ax.set_xlim(mid[0] - 0.62 * span, mid[0] + 0.62 * span)
    ax.set_ylim(mid[1] - 0.62 * span, mid[1] + 0.62 * span)
    if handles:
        fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0), fontsize=8, frameon=False)
    ax.set_aspect("equal")
    ax.grid(True, color="0.9", lw=0.6)
    ax.set_xlabel("u [mm]  (light frame x)")
    ax.set_ylabel("v [mm]  (light frame y)")
    _settle(ax, xlabel_pad=0.25, ylabel_pad=0.4)
    return fig


def coverage_figure(model: LightModel, *, samples=None) -> Figure:
    """The θ (signed by side) each source was sampled at, against the position index."""
    ctx = _context(model, samples=samples)
    return _coverage_figure(ctx, samples)


def _coverage_figure(ctx: _Context, samples=None) -> Figure:
    fig = _new_figure(7.6, 3.9, layout=None)
    ax = _axes_in(fig, 0.75, 0.5, 0.1, 0.1)
    for k, source in enumerate(ctx.model.sources):
        colour = ctx.colours[k]
        if samples is not None and samples.theta.shape[1] == len(ctx.model.sources):
            pos = np.asarray(samples.positions, dtype=float)
            signed = np.degrees(_signed(samples.theta[:, k], samples.phi[:, k], ctx.azimuth))
            ok = np.isfinite(samples.intensity[:, k])
            ax.plot(pos, signed, "-", color=colour, lw=0.8, alpha=0.6)
            ax.plot(pos[ok], signed[ok], "o", color=colour, ms=3.5, label=source.name)
            if np.any(~ok & np.isfinite(signed)):
                ax.plot(pos[~ok], signed[~ok], "x", color=colour, ms=5, label=f"{source.name}: no estimate")
        else:
            d = ctx.data[k]
            order = np.argsort(d.position)
            ax.plot(
                d.position[order],
                np.degrees(_signed(d.theta, d.phi, ctx.azimuth))[order],
                "o-",
                color=colour,
                ms=3.5,
                lw=0.8,
                label=source.name,
            )
    ax.axhline(0.0, color="0.5", lw=0.6)
    ax.set_xlabel("schedule position")
    ax.set_ylabel(f"θ sampled [°]  (+ towards φ = {_deg(ctx.azimuth)})")
    ax.grid(True, color="0.9", lw=0.6)
    ax.legend(fontsize=8, ncols=min(len(ctx.model.sources), 5), loc="best", frameon=False)
    _settle(ax, xlabel_pad=0.25, ylabel_pad=0.4)
    return fig


def angles_figure(
    rays,
    *,
    index: int | None = None,
    centre_m=(0.0, 0.0),
    light_radius_m: float = 0.01,
    ball_half_angle: float | None = None,
    ball_distance_ratio: float | None = None,
) -> Figure:
    """Outgoing angle θ at the light plane against the deflection the ball gives each chief
    ray (the reference paper's Fig. 5), for the chief rays of pixels across the ball.

    Every ray that reaches the light plane is a grey dot; those that land within
    ``light_radius_m`` of ``centre_m`` (the sources) are coloured by their distance from it.
    With ``ball_distance_ratio`` (the camera's distance from the ball's centre over the
    ball's radius) a top axis gives the camera ray's angle off the ball's centre: a ray at
    impact angle α has ``sin(view) = sin α · R/D`` and deflection ``π − 2α``.
    """
    fig = _new_figure(7.2, 4.6, layout=None)
    valid = rays.valid
    defl, theta = np.degrees(rays.deflection[valid]), np.degrees(rays.theta[valid])
    dist = np.hypot(rays.u[valid] - centre_m[0], rays.v[valid] - centre_m[1]) * 1e3
    near = dist <= light_radius_m * 1e3
    top_margin = 0.75 if ball_half_angle is not None and ball_distance_ratio is not None else 0.35
    ax = _axes_in(fig, 0.65, 0.5, 1.15 if np.any(near) else 0.15, top_margin)
    # one marker drawn once and stamped at every ray (a Line2D's markers: far cheaper than a scatter)
    ax.plot(defl, theta, ls="none", marker="o", ms=1.0, mfc="0.75", mew=0.0, label="every chief ray on the light plane")
    if np.any(near):
        order = np.argsort(-dist[near])
        sc = ax.scatter(
            defl[near][order],
            theta[near][order],
            s=5,
            c=dist[near][order],
            cmap="viridis",
            vmin=0.0,
            vmax=light_radius_m * 1e3,
            linewidths=0,
            label=f"rays landing within {light_radius_m * 1e3:.0f} mm of the sources",
        )
        w, h = fig.get_size_inches()
        box = ax.get_position()
        cax = fig.add_axes((1.0 - 0.95 / w, box.y0 + 0.075 * box.height, 0.14 / w, 0.85 * box.height))
        fig.colorbar(sc, cax=cax, label="distance on the light plane from the sources' centre [mm]")
    if ball_half_angle is not None and ball_distance_ratio is not None:
        # the camera's view angle off the ball's centre that gives each deflection (the same for any azimuth)
        k = ball_distance_ratio

        def to_view(defl):
            return np.degrees(np.arcsin(np.clip(np.cos(np.radians(np.asarray(defl, dtype=float)) / 2.0) / k, -1, 1)))

        def to_deflection(view):
            return np.degrees(2.0 * np.arccos(np.clip(np.sin(np.radians(np.asarray(view, dtype=float))) * k, -1, 1)))

        top = ax.secondary_xaxis("top", functions=(to_view, to_deflection))
        top.set_xlabel("the camera's ray: angle off the ball's centre [°]", fontsize=9)
        top.tick_params(labelsize=8)
    ax.set_xlabel("deflection at the ball: angle between the camera's ray and its reflection [°]")
    ax.set_ylabel("outgoing angle θ at the light plane [°]")
    ax.grid(True, color="0.9", lw=0.6)
    ax.legend(fontsize=8, loc="upper right", markerscale=4, frameon=False)
    _settle(ax, xlabel_pad=0.25, ylabel_pad=0.35)
    title = "chief rays across the ball" + (f", position {index}" if index is not None else "")
    if ball_half_angle is not None:
        title += f": the ball spans ±{math.degrees(ball_half_angle):.1f}° of the camera's view"
    fig.suptitle(title, fontsize=10)
    return fig


def residuals_figure(model: LightModel, *, samples=None) -> Figure:
    """Per source, the normalised residuals ``(data − fit)/σ`` against θ (signed by side)."""
    ctx = _context(model, samples=samples)
    return _residuals_figure(ctx)


def _residuals_figure(ctx: _Context) -> Figure:
    n = len(ctx.model.sources)
    rows, cols = _grid(n)
    width, height = 3.6 * cols, 2.4 * rows
    fig = _new_figure(width, height, layout=None)
    left, right, bottom, top, wgap, hgap = 0.75, 0.12, 0.5, 0.3, 0.5, 0.8  # inches
    grid = fig.add_gridspec(
        rows,
        cols,
        left=left / width,
        right=1.0 - right / width,
        bottom=bottom / height,
        top=1.0 - top / height,
        wspace=wgap / ((width - left - right - (cols - 1) * wgap) / cols),
        hspace=hgap / ((height - bottom - top - (rows - 1) * hgap) / rows),
    )
    axes = []
    for k, source in enumerate(ctx.model.sources):
        ax = fig.add_subplot(grid[divmod(k, cols)], sharey=axes[0] if axes else None)
        axes.append(ax)
        d = ctx.data[k]
        signed = np.degrees(_signed(d.theta, d.phi, ctx.azimuth))
        with np.errstate(invalid="ignore", divide="ignore"):
            r = (d.intensity - source.fit(d.theta, d.phi)) / d.sigma
        ax.axhspan(-3, 3, color="0.93", lw=0)
        ax.axhspan(-1, 1, color="0.85", lw=0)
        ax.axhline(0, color="0.4", lw=0.7)
        ax.plot(signed, r, "o", color=ctx.colours[k], ms=3.5, mec="k", mew=0.3)
        ax.set_title(f"{source.name}: χ²ᵣ = {source.fit.chi2_reduced:.3g}", fontsize=9, y=1.0)  # y: no overlap search
        ax.grid(True, color="0.9", lw=0.5)
        if k % cols == 0:
            ax.set_ylabel("(data − fit) / σ")
        if k >= n - cols:
            ax.set_xlabel("θ [°] (signed by side)")
        ax.tick_params(labelsize=8, labelleft=k % cols == 0)  # one y scale, read off the left column
    for ax in axes:
        _settle(ax, xlabel_pad=0.25, ylabel_pad=0.45)
    return fig


# --- geometry from the run --------------------------------------------------------------------------
def _middle_position(run, samples) -> _Geometry:
    """The sweep's middle position: its index, the light's pose there and the rig's geometry (no ray yet)."""
    from processing.trace import RigGeometry, light_pose_at

    rig = run.header.rig
    geometry = RigGeometry.from_rig(rig)
    positions = np.asarray(samples.positions) if samples is not None and len(samples.positions) else None
    if positions is None:
        positions = np.asarray(run.completed_positions())
    if positions.size == 0:
        positions = np.arange(run.n_positions)
    index = int(positions[len(positions) // 2])
    measured = None
    try:
        measured = run.measured_pose(index)
    except (ValueError, KeyError, OSError):
        measured = None
    pose = light_pose_at(geometry, measured if measured is not None else run.header.tool_poses[index])
    return _Geometry(index, pose, geometry)


def _trace_middle(position: _Geometry, model: LightModel, max_pixels: int = 60_000) -> _Geometry:
    """``position`` with the chief rays of (at most about ``max_pixels``) pixels across the ball, and the
    footprint on the light plane of the pixel whose chief ray lands nearest the sources."""
    from processing.trace import ball_pixel_box, box_pixels, grid_stride, trace_pixels

    geometry, pose = position.geometry, position.pose
    out = replace(position)
    box = ball_pixel_box(geometry)
    stride = grid_stride(box, max_pixels)
    cols, rows = box_pixels(box, stride)
    rays = trace_pixels(geometry, pose, cols, rows)
    out.rays = rays
    centroid = np.mean([s.centre_m for s in model.sources], axis=0)
    if np.any(rays.valid):
        dist = np.where(rays.valid, np.hypot(rays.u - centroid[0], rays.v - centroid[1]), np.inf)
        i = int(np.argmin(dist))
        col, row = rays.cols[i], rays.rows[i]
        if stride > 1:  # refine on the full pixel grid around the best subsampled pixel
            cc, rr = np.meshgrid(np.arange(col - stride, col + stride + 1), np.arange(row - stride, row + stride + 1))
            fine = trace_pixels(geometry, pose, cc.ravel(), rr.ravel())
            d2 = np.where(fine.valid, np.hypot(fine.u - centroid[0], fine.v - centroid[1]), np.inf)
            j = int(np.argmin(d2))
            col, row = fine.cols[j], fine.rows[j]
        corners = trace_pixels(
            geometry, pose, col + np.array([-0.5, 0.5, 0.5, -0.5]), row + np.array([-0.5, -0.5, 0.5, 0.5])
        )
        if np.all(corners.valid):
            out.pixel_polygon = np.column_stack([corners.u, corners.v])
            out.pixel_at = (float(col), float(row))
    return out


# --- the calibration check ----------------------------------------------------------------------------
def _calibration_section(model: LightModel, run, report, calibration, geo: _Geometry | None) -> str:
    rig = run.header.rig if run is not None else None
    found = calibration
    if found is None and report is not None:
        found = getattr(report, "calibration", None)
    if found is None:
        found = model.provenance.get("calibration")
    if found is None and run is not None and callable(getattr(run, "calibration_image", None)):
        image = run.calibration_image()
        if image is not None:
            from processing.calibration import calibrate_ball

            found = calibrate_ball(image, rig)
    parts = []
    comparison = None
    if found is None:
        parts.append(_note(f"{NO_CALIBRATION}: the processing used the ball centre of the rig description."))
    elif isinstance(found, dict):
        comparison = found
    elif rig is not None and hasattr(found, "centre_camera"):
        from processing.calibration import compare_with_rig

        comparison = compare_with_rig(found, rig)
    else:
        parts.append(_note("a calibration result is present, but without the run's rig it cannot be compared."))
    if comparison is not None:
        rows = []
        for label, key in (
            ("measured (rig frame)", "measured_mm"),
            ("described by the rig", "described_mm"),
            ("measured − described", "discrepancy_mm"),
            ("1σ of the measurement", "sigma_mm"),
        ):
            value = comparison.get(key)
            if value is not None:
                fmt = "{:.3f}" if key == "sigma_mm" else "{:+.3f}"
                rows.append([label, *(fmt.format(float(v)) for v in value)])
        parts.append(_table(["ball centre [mm]", "x", "y", "z"], rows))
        distance, significance = comparison.get("distance_mm"), comparison.get("significance")
        if distance is not None:
            text = f"The ball is {float(distance):.3f} mm from where the rig description puts it"
            if significance is not None:
                text += f" ({float(significance):.1f} σ of the measurement)"
            parts.append(f"<p>{html.escape(text)}.</p>")
    if rig is not None and geo is not None:
        try:
            from processing.calibration import angle_sensitivity
        except ImportError:
            angle_sensitivity = None
        if angle_sensitivity is not None:
            sens = angle_sensitivity(rig, geo.pose, 1e-3, max_pixels=40_000)
            rows = [
                [
                    axis,
                    f"{sens[axis]['theta_median_deg']:.3f}",
                    f"{sens[axis]['theta_max_deg']:.3f}",
                    f"{sens[axis]['direction_median_deg']:.3f}",
                    f"{sens[axis]['uv_median_mm']:.3f}",
                ]
                for axis in "xyz"
            ]
            parts.append(
                f"<p>What 1 mm of error in the ball's position costs, at position {geo.index} "
                f"(chief rays landing within {sens['plane_radius_mm']:.0f} mm of the light's axis):</p>"
            )
            parts.append(
                _table(
                    [
                        "ball moved 1 mm along",
                        "Δθ median [°]",
                        "Δθ max [°]",
                        "Δdirection median [°]",
                        "Δ(u, v) median [mm]",
                    ],
                    rows,
                )
            )
            if comparison is not None and comparison.get("distance_mm") is not None:
                shift = float(comparison["distance_mm"]) * sens["theta_median_deg"]
                parts.append(
                    f"<p>At the measured discrepancy that is about {shift:.3f}° of θ (median, worst axis).</p>"
                )
    return "\n".join(parts)


# --- HTML ---------------------------------------------------------------------------------------------
def _note(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


def _table(header: list[str] | None, rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header) if header else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return (f"<table><thead><tr>{head}</tr></thead>" if head else "<table>") + f"<tbody>{body}</tbody></table>"


def _img(png: bytes, alt: str, cls: str = "") -> str:
    data = base64.b64encode(png).decode("ascii")
    extra = f' class="{cls}"' if cls else ""
    return f'<img src="data:image/png;base64,{data}" alt="{html.escape(alt)}"{extra}>'


def _figure(fig: Figure, alt: str, caption: str, encoder: _Encoder | None = None) -> str:
    if encoder is not None:
        return encoder.figure(fig, alt, caption)
    return f"<figure>{_img(_png(fig), alt)}<figcaption>{caption}</figcaption></figure>"


def _mm(x: float) -> str:
    return f"{1e3 * x:.2f} mm" if math.isfinite(x) else "unknown"


def _param_rows(source: SourceModel, units: str) -> list[list[str]]:
    rows = []
    for name, value in source.fit.params.items():
        err = source.fit.uncertainties.get(name, float("nan"))
        if name in ("sigma", "sigma1", "sigma2", "theta0", "phi0"):
            shown, unc, unit = math.degrees(value), math.degrees(err) if math.isfinite(err) else err, "°"
        elif name == "a":
            shown, unc, unit = value, err, units
        elif name == "mu":
            shown, unc, unit = value, err, ""
        elif re.fullmatch(r"c\d+", name):
            power = int(name[1:])
            shown, unc, unit = value, err, units + (f"/rad^{power}" if power else "")
        else:
            shown, unc, unit = value, err, ""
        unc_text = "not determined" if not math.isfinite(unc) else f"{unc:.3g}"
        relative = f"{abs(unc / shown) * 100:.2g} %" if math.isfinite(unc) and shown != 0 else ""
        rows.append([source.name, name, f"{shown:.5g}", unc_text, relative, unit])
    return rows


def _half_width(source: SourceModel) -> float | None:
    """θ where the fit falls to half its value on the axis (degrees), if it does before 90°."""
    theta = np.radians(np.linspace(0.0, 90.0, 1801))
    values = source.intensity(theta)
    if values[0] <= 0:
        return None
    below = np.flatnonzero(values <= 0.5 * values[0])
    return float(np.degrees(theta[below[0]])) if below.size else None


_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; max-width: 1180px; margin: 1.5em auto;
       padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
th { background: #f2f2f2; } td { font-variant-numeric: tabular-nums; }
figure { margin: 0.8em 0; } figure img { max-width: 100%; }
figcaption, .caption { font-size: 0.92em; color: #444; max-width: 60em; }
.note { color: #7a4b00; background: #fff6e0; padding: 0.4em 0.7em; border-left: 3px solid #e0a000; }
.strip { display: flex; flex-wrap: wrap; gap: 0.6em; } .strip figure { margin: 0; }
.strip img { width: 180px; } .strip figcaption { text-align: center; }
"""


def _previews(report, run, model: LightModel, path: Path) -> list[Path]:
    outputs = getattr(report, "outputs", None) or {}
    pngs = [Path(p) for p in outputs.get("png", [])]
    if not pngs:
        stems = []
        if report is not None:
            stems.append(Path(report.results_file).parent / f"{Path(report.run_file).stem}.hdr")
        if run is not None:
            stems.append(path.parent / f"{Path(run.path).stem}.hdr")
            stems.append(Path(run.path).parent / f"{Path(run.path).stem}.hdr")
        if model.provenance.get("run_file"):
            run_file = Path(model.provenance["run_file"])
            stems += [path.parent / f"{run_file.stem}.hdr", run_file.parent / f"{run_file.stem}.hdr"]
        for folder in stems:
            if folder.is_dir():
                pngs = sorted(folder.glob("position-*.png"))
                if pngs:
                    break
    return [p for p in pngs if p.exists()]


def _ball_box(geo: _Geometry | None):
    """The ball's image as ``(col, row, radius, sensor width)`` in sensor pixels, to crop the previews."""
    if geo is None:
        return None
    g = geo.geometry
    centre = g.project(g.ball_centre[None, :])[0]
    distance = float(np.linalg.norm(g.ball_centre - g.camera_centre))
    radius = g.K[0, 0] * math.tan(math.asin(min(1.0, g.ball_radius / distance)))
    return float(centre[0]), float(centre[1]), 1.15 * radius, g.width


def _preview_strip(pngs: list[Path], box=None) -> str:
    import cv2

    picks = sorted(set(np.linspace(0, len(pngs) - 1, min(_PREVIEWS, len(pngs))).round().astype(int).tolist()))
    cells = []
    for i in picks:
        image = cv2.imread(str(pngs[i]), cv2.IMREAD_COLOR)
        if image is None:
            continue
        if box is not None:  # the ball only: the rest of the frame is dark
            scale = image.shape[1] / box[3]
            col, row, radius = box[0] * scale, box[1] * scale, max(box[2] * scale, 4.0)
            r0, r1 = max(0, int(row - radius)), min(image.shape[0], int(math.ceil(row + radius)))
            c0, c1 = max(0, int(col - radius)), min(image.shape[1], int(math.ceil(col + radius)))
            if r1 - r0 >= 4 and c1 - c0 >= 4:
                image = image[r0:r1, c0:c1]
                zoom = _PREVIEW_CROP / image.shape[1]
                size = (_PREVIEW_CROP, max(1, round(image.shape[0] * zoom)))
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA if zoom < 1 else cv2.INTER_CUBIC)
                ring = (round((col - c0) * zoom * 8), round((row - r0) * zoom * 8))  # 3 bits of sub-pixel
                cv2.circle(image, ring, round(radius / 1.15 * zoom * 8), (110, 110, 110), 1, cv2.LINE_AA, 3)
        if image.shape[1] > _PREVIEW_WIDTH:
            size = (_PREVIEW_WIDTH, max(1, round(image.shape[0] * _PREVIEW_WIDTH / image.shape[1])))
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        ok, encoded = cv2.imencode(".png", image)
        if not ok:
            continue
        match = re.search(r"(\d+)", pngs[i].stem)
        label = f"position {int(match.group(1))}" if match else pngs[i].stem
        cells.append(f"<figure>{_img(encoded.tobytes(), label)}<figcaption>{html.escape(label)}</figcaption></figure>")
    return f'<div class="strip">{"".join(cells)}</div>' if cells else ""


def _header(model: LightModel, run, report, samples, resolution_m: float) -> str:
    prov = model.provenance
    header = run.header if run is not None else None
    run_id = prov.get("run_id") or (header.run_id if header else None) or "unknown"
    rig = prov.get("rig") or (header.rig.name if header else None) or "unknown"
    rows = [["run", run_id], ["rig", rig]]
    if header is not None:
        rows.append(["run started (UTC)", header.created_utc])
    rows.append(["report written (UTC)", datetime.now(UTC).strftime("%Y-%m-%d %H:%M:%S")])
    if run is not None:
        rows.append(["positions", f"{len(run.completed_positions())} complete of {run.n_positions} scheduled"])
    n = [len(d.theta) for d in _source_data(model, samples)]
    rows.append(
        [
            "sources",
            f"{len(model.sources)} ({', '.join(s.name for s in model.sources)}), {min(n)}–{max(n)} samples each"
            if n
            else str(len(model.sources)),
        ]
    )
    if model.units == "W/sr":
        rows.append(["units", "W/sr (radiometrically calibrated)"])
    else:
        rows.append(
            [
                "units",
                f"{model.units} (not calibrated: the shapes and the ratios between sources are "
                "measured, not the absolute scale)",
            ]
        )
    estimator = getattr(report, "estimator", "") or prov.get("method") or "not recorded"
    reason = getattr(report, "estimator_reason", "") or prov.get("estimator_reason")
    rows.append(
        ["estimator", f"{estimator}: {reason}" if reason else f"{estimator} (why is not recorded in the light model)"]
    )
    rows.append(
        [
            "spatial resolution on the light plane",
            f"{_mm(resolution_m)}: the point spread's footprint, the patch of the light plane one pixel "
            "gathers light from; sources closer than this are told apart only by unmixing with templates",
        ]
    )
    noise = getattr(report, "noise", None)
    if noise is not None:
        where = {"rig": "the rig's camera figures", "estimated": "estimated from the brackets"}.get(
            noise.source, noise.source
        )
        converted = (
            f"; intensities converted to e⁻/s with the rig's calibrated gain, {prov['gain_e_per_dn']:.4g} e⁻/DN"
            if prov.get("gain_source") == "rig" and prov.get("gain_e_per_dn")
            else ""
        )
        rows.append(
            [
                "noise model",
                f"gain {noise.gain_e_per_dn:.4g} e⁻/DN, read noise {noise.read_noise_dn:.4g} DN "
                f"(photon shot + read noise, from {where}: it weights the merge){converted}",
            ]
        )
    else:
        rows.append(["noise model", "not given to the report"])
    if prov.get("layout"):
        rows.append(["layout of the sources", str(prov["layout"])])
    for label, key, digits in (
        ("camera aperture", "aperture_m", ".4g"),
        ("sensor distance", "sensor_distance_m", ".3f"),
    ):
        record = prov.get(key)
        if isinstance(record, dict) and record.get("fitted_m"):
            rows.append([label, describe_fitted(record, digits)])
        elif isinstance(record, str) and "failed" in record:
            rows.append([label, record])
    fits = sorted({s.fit.method for s in model.sources})
    rows.append(["fit", ", ".join(fits)])
    if prov.get("software_version"):
        rows.append(["software", f"mirrorgonio {prov['software_version']}"])
    return _table(None, [[f"{name}:", value] for name, value in rows])


# --- sections drawn by a cluster's workers ---------------------------------------------------------
#: The sections drawn from the context alone (the model, the samples and the middle position's chief
#: rays): a cluster's workers can draw them, each in its own process, while this process draws the
#: rest. Drawing is mostly matplotlib's text rendering, Python holding the GIL: threads would not
#: share it out, processes do. Measured on 2 cores, a whole run's page: 0.62 s in one process, of
#: which these five sections 0.5 s (50-150 ms each); 0.37-0.55 s with two workers drawing them.
_REMOTE_SECTIONS: dict[str, Callable[[_Context, object], str]] = {
    _SECTIONS[0]: lambda ctx, samples: _intensity_section(ctx),
    _SECTIONS[1]: lambda ctx, samples: _layout_section(ctx),
    _SECTIONS[2]: lambda ctx, samples: _coverage_section(ctx, samples),
    _SECTIONS[3]: lambda ctx, samples: _angles_section(ctx),
    _SECTIONS[4]: lambda ctx, samples: _residuals_section(ctx),
}


#: The remote sections that read the chief rays themselves (the others get the context without them).
_NEEDS_RAYS = frozenset({_SECTIONS[3]})


def warm_up_drawing() -> None:
    """Draw and encode a tiny figure with text: matplotlib's fonts and Agg loaded, so that the
    first section a fresh worker draws costs what the next ones do."""
    fig = _new_figure(2.0, 1.0, layout=None)
    ax = fig.add_subplot()
    ax.errorbar([0, 1], [0, 1], yerr=[0.1, 0.1], fmt="o", label="σ χ²ᵣ")
    ax.set_xlabel("θ [°]", fontsize=8)
    ax.set_title("source", fontweight="bold")
    ax.legend(fontsize=8, frameon=False)
    _png(fig)


def draw_section(name: str, ctx: _Context, samples) -> str:
    """One of :data:`_REMOTE_SECTIONS` drawn here, its figures encoded here: a task a Dask
    worker runs for :func:`write_report`."""
    ctx = replace(ctx, encoder=None)
    return _guarded(name, lambda: _REMOTE_SECTIONS[name](ctx, samples))


class _RemoteSections:
    """The sections :func:`write_report` hands to a cluster's workers; each one the workers
    could not draw is drawn here when asked for, with the same result."""

    def __init__(self, compute, samples):
        self.compute = compute if compute is not None and getattr(compute, "dask", False) else None
        self.samples = samples
        self.futures: dict[str, object] = {}

    def start(self, name: str, ctx: _Context) -> None:
        if self.compute is None:
            return
        shipped = replace(ctx, encoder=None)
        if name not in _NEEDS_RAYS and ctx.geometry is not None:  # the rays are most of its bytes (~6 MB)
            shipped.geometry = replace(ctx.geometry, rays=None)
        try:
            self.futures[name] = self.compute.submit(draw_section, name, shipped, self.samples)
        except Exception as exc:  # noqa: BLE001 - e.g. a truth callable that does not pickle: draw it here
            log.info("report: %s drawn in this process (%s: %s)", name, type(exc).__name__, exc)

    def result(self, name: str, ctx: _Context) -> str:
        future = self.futures.pop(name, None)
        if future is not None:
            try:
                return future.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker, an unpicklable result: draw it here
                log.warning(
                    "report: %s: the worker could not draw it (%s: %s); drawn here", name, type(exc).__name__, exc
                )
        return _guarded(name, lambda: _REMOTE_SECTIONS[name](ctx, self.samples))


def write_report(
    path, model: LightModel, *, run=None, samples=None, report=None, truth=None, calibration=None, compute=None
) -> Path:
    """Write the run's report: one self-contained HTML file.

    Parameters
    ----------
    path : path-like
        The HTML file to write (its folder is created).
    model : LightModel
        The measured light.
    run : RunFile, optional
        The (open) run file: its rig and poses give the chief-ray figure, the pixel's
        footprint and the calibration's sensitivity. Without it those say so.
    samples : SourceSamples, optional
        The pipeline's per-position samples (every position, including those without an
        estimate); without them the model's sample tables are used.
    report : ProcessReport, optional
        The pipeline's report: estimator and its reason, noise model, spatial resolution
        and the HDR previews.
    truth : callable, optional
        ``truth(source, theta) -> intensity`` for a simulated run (see the module's notes).
    calibration : BallFit or dict, optional
        A calibration of the ball's position (:func:`processing.calibration.calibrate_ball`,
        or :func:`~processing.calibration.compare_with_rig`'s dict). Also looked for on
        ``report.calibration``, in ``model.provenance["calibration"]`` and, when the run file
        offers one, in ``run.calibration_image()``; without any the section says
        "no calibration image in this run".
    compute : processing.parallel.Compute, optional
        A Dask cluster (the processing's): its workers draw the sections that need only the
        model and the samples (:data:`_REMOTE_SECTIONS`) while this process draws the others.
        A section a worker cannot draw (the inputs do not pickle, the worker is lost) is drawn
        here instead; the page is the same either way.

    Returns
    -------
    Path
        The file written.
    """
    # The report makes some 10⁵ short-lived objects (matplotlib's artists hold reference cycles), which
    # can set off a full collection: with the process's objects set aside (frozen) it walks only the
    # report's own, instead of everything the processing built (0.1-0.3 s on a whole run's heap).
    # A process that froze objects itself manages its collector: it is left alone.
    freeze = gc.get_freeze_count() == 0
    if freeze:
        gc.freeze()
    try:
        return _write_report(Path(path), model, run, samples, report, truth, calibration, compute)
    finally:
        if freeze:
            gc.unfreeze()


def _guarded(title: str, build: Callable[[], str]) -> str:
    """A section's HTML, or a note saying why it could not be drawn (one section's failure never stops the page)."""
    try:
        return build()
    except Exception as exc:  # noqa: BLE001
        log.warning("report: %s: %s", title, exc, exc_info=True)
        return _note(f"this section could not be drawn: {type(exc).__name__}: {exc}")


def _write_report(path: Path, model: LightModel, run, samples, report, truth, calibration, compute=None) -> Path:
    resolution = float(model.provenance.get("spatial_resolution_m") or float("nan"))
    if not math.isfinite(resolution) and report is not None:
        resolution = float(getattr(report, "spatial_resolution_m", float("nan")))
    ctx = _context(model, samples=samples, truth=truth, resolution_m=resolution)

    def traced(step: Callable[[], _Geometry]) -> _Geometry | None:
        try:
            return step()
        except Exception as exc:  # a figure never stops the processing
            log.warning("report: chief rays at the middle position: %s", exc, exc_info=True)
            ctx.geometry_note = f"the chief rays could not be traced: {exc}"
            return None

    intensity, layout, coverage, angles, residuals, calibrated, previews = _SECTIONS
    # The workers start on the sections that need no chief rays while this process traces them;
    # those that need them follow the trace. This process's worker thread meanwhile takes the
    # calibration and the previews.
    elsewhere = _RemoteSections(compute, samples)
    for name in (intensity, residuals, coverage):
        elsewhere.start(name, ctx)
    position = None
    if run is None:
        ctx.geometry_note = "no run file given to the report: the rig and the poses are unknown"
    else:
        position = traced(lambda: _middle_position(run, samples))
    # One worker thread takes what runs mostly in C, outside the GIL, while this thread draws: the
    # calibration's sensitivity (numpy on large arrays: it overlaps the trace below), the previews'
    # decoding and the figures' PNG encoding (OpenCV, ISA-L). Its tasks run in the order given.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="mirrorgonio-report") as pool:
        ctx.encoder = _Encoder(pool)
        built: dict[str, str | Future] = {
            calibrated: pool.submit(
                _guarded, calibrated, lambda: _calibration_section(model, run, report, calibration, position)
            ),
            previews: pool.submit(_guarded, previews, lambda: _previews_section(report, run, model, path, position)),
        }
        if position is not None:
            ctx.geometry = traced(lambda: _trace_middle(position, model))
        for name in (angles, layout):
            elsewhere.start(name, ctx)
        for name in (intensity, residuals, coverage, angles, layout):  # drawn here if not by a worker
            built[name] = elsewhere.result(name, ctx)
        run_id = model.provenance.get("run_id") or (run.header.run_id if run is not None else "")
        title = f"mirrorgonio light report: {run_id}" if run_id else "mirrorgonio light report"
        body = [f"<h1>{html.escape(title)}</h1>", _header(model, run, report, samples, resolution)]
        for name in _SECTIONS:
            content = built[name].result() if isinstance(built[name], Future) else built[name]
            body.append(f"<h2>{html.escape(name)}</h2>\n{ctx.encoder.fill(content)}")
    page = (
        f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{html.escape(title)}</title>\n'
        f"<style>{_CSS}</style>\n</head>\n<body>\n" + "\n".join(body) + "\n</body>\n</html>\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(path)
    return path


# --- the sections -------------------------------------------------------------------------------------
def _intensity_section(ctx: _Context) -> str:
    model = ctx.model
    side = f"{_deg(ctx.azimuth)}"
    caption = (
        f"Radiant intensity of each source [{model.units}] against the angle θ from the light's axis "
        f"(up), the radius being the intensity. Dots are the samples (one per position, bars ±1σ); the solid "
        f"line is the fit where the samples cover θ (grey wedges), dashed where it extrapolates — read "
        f"nothing into the dashed part. θ is signed by side: + for directions towards azimuth φ = {side} in "
        f"the light frame, − for the opposite side; the fitted model is rotationally symmetric unless it "
        f"is a 2-D one. "
    )
    if any(d.cell_sum is not None for d in ctx.data):
        caption += (
            "Open triangles are the chief-ray cell sums at the same positions: the light a cell of the "
            "sharp-looking (u, v) map holds; their distance from the dots is what unmixing with the "
            "point spread recovers. "
        )
    if ctx.truth is not None:
        caption += "The broken black line is the truth of the simulation."
    parts = [_figure(_polar_figure(ctx), "radiant intensity per source, half-polar", html.escape(caption), ctx.encoder)]
    header = [
        "source",
        "(u, v) [mm]",
        "radius [mm]",
        f"on-axis I [{model.units}]",
        "half-width at half max",
        "θ covered",
        "samples",
        "χ²ᵣ",
    ]
    if ctx.truth is not None:
        header.append("error vs truth (RMS / peak)")
    rows = []
    for k, (source, d) in enumerate(zip(model.sources, ctx.data, strict=True)):
        lo, hi = source.fit.theta_range
        hw = _half_width(source)
        row = [
            source.name,
            f"({1e3 * source.centre_m[0]:+.2f}, {1e3 * source.centre_m[1]:+.2f})",
            f"{1e3 * source.radius_m:.2f}",
            f"{float(source.intensity(0.0)):.4g}",
            f"{hw:.1f}°" if hw is not None else "beyond 90°",
            f"{math.degrees(lo):.1f}° – {math.degrees(hi):.1f}°",
            str(len(d.theta)),
            f"{source.fit.chi2_reduced:.3g}",
        ]
        if ctx.truth is not None:
            err = _truth_error(source, ctx.truth, k)
            row.append(f"{100 * err:.3g} %" if err is not None else "no truth for this source")
        rows.append(row)
    parts.append(_table(header, rows))
    if ctx.truth is not None:
        parts.append(
            "<p>Error vs truth: RMS(I<sub>fit</sub> − I<sub>true</sub>) / max(I<sub>true</sub>) over the θ "
            "the source's samples cover (<code>measurement.md</code>).</p>"
        )
    return "\n".join(parts)


def _layout_section(ctx: _Context) -> str:
    polygon = ctx.geometry.pixel_polygon if ctx.geometry is not None else None
    fig = layout_figure(ctx.model, resolution_m=ctx.resolution_m, pixel_polygon=polygon)
    caption = (
        "The sources where the layout puts them on the light plane (circles of their emitting radius), "
        "seen from the front (the light emits towards the viewer). "
    )
    if math.isfinite(ctx.resolution_m):
        caption += (
            f"The dashed circle, drawn to the same scale, is the patch one camera pixel gathers light from "
            f"(the point spread's footprint, {_mm(ctx.resolution_m)} across): where it covers several "
            f"sources, a pixel mixes them and only the templates' unmixing tells them apart. "
        )
    if polygon is not None:
        caption += (
            f"The small black patch is where one pixel's chief ray alone would look (pixel "
            f"{ctx.geometry.pixel_at[0]:.0f}, {ctx.geometry.pixel_at[1]:.0f} at position "
            f"{ctx.geometry.index}): sharp, but not what the pixel sees."
        )
    parts = [_figure(fig, "sources on the light plane", html.escape(caption), ctx.encoder)]
    if not math.isfinite(ctx.resolution_m):
        parts.append(_note("the spatial resolution is not recorded in the light model: no footprint drawn."))
    if polygon is None and ctx.geometry_note:
        parts.append(_note(f"no chief-ray footprint: {ctx.geometry_note}."))
    return "\n".join(parts)


def _coverage_section(ctx: _Context, samples) -> str:
    caption = (
        "The angle θ each source's sample leaves at, position by position (signed by side as in the polar "
        "plots). A sweep past the ball draws one line per source crossing 0 near the middle; the gaps "
        "between the lines are the sources' different view of the ball. The fits are valid over the θ "
        "range each line spans."
    )
    if samples is not None:
        caption += " Crosses mark positions where the source was in view but had no estimate."
    return _figure(_coverage_figure(ctx, samples), "theta sampled per position", html.escape(caption), ctx.encoder)


def _angles_section(ctx: _Context) -> str:
    geo = ctx.geometry
    if geo is None or geo.rays is None:
        return _note(f"skipped: {ctx.geometry_note or 'no run file'}.")
    rays = geo.rays
    if not np.any(rays.valid):
        return _note(f"skipped: no chief ray reaches the light plane at position {geo.index}.")
    centres = np.array([s.centre_m for s in ctx.model.sources])
    centroid = centres.mean(axis=0)
    extent = float(np.max(np.hypot(*(centres - centroid).T) + [s.radius_m for s in ctx.model.sources]))
    reach = max(extent + 1e-3, 0.5 * ctx.resolution_m if math.isfinite(ctx.resolution_m) else 0.0, 5e-3)
    g = geo.geometry
    distance = float(np.linalg.norm(g.ball_centre - g.camera_centre))
    half = math.asin(min(1.0, g.ball_radius / distance))
    fig = angles_figure(
        rays,
        index=geo.index,
        centre_m=tuple(centroid),
        light_radius_m=reach,
        ball_half_angle=half,
        ball_distance_ratio=distance / g.ball_radius,
    )
    valid = rays.valid
    near = valid & (np.hypot(rays.u - centroid[0], rays.v - centroid[1]) <= reach)
    d_all = np.degrees(rays.deflection[valid])
    t_all = np.degrees(rays.theta[valid])
    caption = (
        f"Each dot is the chief ray of one pixel on the ball at position {geo.index} (the middle of the "
        f"sweep). The camera sees the whole ball within ±{math.degrees(half):.1f}°; the convex mirror turns "
        f"those rays by {d_all.min():.0f}°–{d_all.max():.0f}°, so they leave the light plane over θ = "
        f"{t_all.min():.0f}°–{t_all.max():.0f}°: one photograph samples a wide cone of directions, which is "
        f"what lets a short sweep measure I(θ). "
    )
    if np.any(near):
        t_near = np.degrees(rays.theta[near])
        caption += (
            f"The coloured dots are the rays that land on the sources (within {1e3 * reach:.0f} mm of their "
            f"centre): at this position they carry θ = {t_near.min():.1f}°–{t_near.max():.1f}°, the "
            "spread the camera's blur mixes into one sample."
        )
    return _figure(fig, "outgoing angle against deflection", html.escape(caption), ctx.encoder)


def _residuals_section(ctx: _Context) -> str:
    caption = (
        "Data minus fit at each sample, in units of the sample's σ (dark band ±1σ, light band ±3σ). "
        "A good fit scatters evenly about 0, mostly within the dark band, and has χ²ᵣ near 1; a wave or a "
        "trend with θ means the model's shape does not match the source."
    )
    parts = [_figure(_residuals_figure(ctx), "normalised residuals per source", html.escape(caption), ctx.encoder)]
    rows = []
    for source in ctx.model.sources:
        rows.extend(_param_rows(source, ctx.model.units))
    parts.append(
        "<p>The fitted parameters, with their 1σ uncertainties (from the covariance of the weighted fit; "
        "angles in degrees):</p>"
    )
    parts.append(_table(["source", "parameter", "value", "± 1σ", "relative", "unit"], rows))
    warnings = [f"{s.name}: {s.fit.info['warning']}" for s in ctx.model.sources if s.fit.info.get("warning")]
    parts.extend(_note(w) for w in warnings)
    return "\n".join(parts)


def _previews_section(report, run, model: LightModel, path: Path, geo: _Geometry | None) -> str:
    pngs = _previews(report, run, model, path)
    if not pngs:
        return _note("no HDR previews found (the hdr step writes them beside the results as position-NNN.png).")
    box = _ball_box(geo)
    strip = _preview_strip(pngs, box)
    if not strip:
        return _note("the HDR previews could not be read.")
    caption = (
        f"{min(_PREVIEWS, len(pngs))} of the {len(pngs)} merged HDR frames, spread over the sweep "
        f"(tone-mapped: square root of the radiance{', cropped to the ball' if box else ''}). The light "
        "appears as a blurred spot, its reflection on the ball, that moves across the ball as the light "
        "passes."
    )
    return f"{strip}<p class='caption'>{html.escape(caption)}</p>"


# --- reflectance (processing.reflectance) ---------------------------------------------------------------
_METHOD_NAMES = {"collimated": "collimated", "isotropic": "isotropic point", "measured": "measured near-field model"}


def reflectance_profiles_figure(profiles: dict, methods=("collimated", "isotropic", "measured")) -> Figure:
    """ρ along the object's vertical axis, one panel per light model (the reference paper's Fig. 11).

    ``profiles`` is :func:`processing.reflectance.reflectance_profiles`'s dict: per height bin
    the median (line) and the interquartile band (shaded) of the channel mean of ρ. The
    measured model's overall median is drawn in every panel as a dashed line, for scale.
    """
    methods = [m for m in methods if m in profiles]
    fig = _new_figure(3.6 * max(len(methods), 1), 4.6)
    axes = fig.subplots(1, max(len(methods), 1), sharex=True, sharey=True, squeeze=False)[0]
    height = 1e3 * np.asarray(profiles.get("height_m", []), dtype=float)
    reference = None
    if "measured" in profiles:
        med = np.asarray(profiles["measured"]["median"], dtype=float)
        counts = np.asarray(profiles["measured"]["count"], dtype=float)
        ok = np.isfinite(med)
        if ok.any():
            reference = float(np.average(med[ok], weights=counts[ok]))
    for ax, m, colour in zip(axes, methods, _COLOURS, strict=False):
        p = profiles[m]
        med, q25, q75 = (np.asarray(p[k], dtype=float) for k in ("median", "q25", "q75"))
        ok = np.isfinite(med)
        if ok.any():
            ax.fill_betweenx(height[ok], q25[ok], q75[ok], color=colour, alpha=0.25, lw=0, label="interquartile range")
            ax.plot(med[ok], height[ok], color=colour, lw=2, label="median")
        if reference is not None:
            ax.axvline(reference, color="k", ls="--", lw=0.8, label="measured model, overall")
        ax.set_title(_METHOD_NAMES.get(m, m))
        ax.set_xlabel("albedo ρ (mean of R, G, B)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("height along the object's vertical axis [mm]")
    if methods:
        axes[0].legend(loc="best", fontsize=8)
    return fig


def _swatch(rgb) -> str:
    r, g, b = (int(c) for c in rgb)
    return (
        f'<span style="display:inline-block;width:1.2em;height:1em;border:1px solid #888;'
        f'background:rgb({r},{g},{b})"></span>'
    )


def _fmt(value, digits: int = 4) -> str:
    if value is None:
        return "—"
    if isinstance(value, (list, tuple)):
        return ", ".join(_fmt(v, digits) for v in value)
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    return f"{v:.{digits}g}" if math.isfinite(v) else "—"


def reflectance_section(summary: dict, images: dict | None = None) -> str:
    """The reflectance results as an HTML fragment (headings ``<h2>`` and below).

    Parameters
    ----------
    summary : dict
        The ``reflectance.json`` summary (:func:`processing.reflectance.write_outputs`).
    images : dict of str to path-like, optional
        PNG files embedded: ``albedo-<method>``, ``reasons``, ``profiles`` and
        ``texture-<method>``.
    """
    from processing.reflectance import PIXEL_CODES, PIXEL_COLOURS, PIXEL_SHORT, SAMPLE_CODES, SAMPLE_SHORT

    images = {k: Path(v) for k, v in (images or {}).items() if v is not None and Path(v).is_file()}
    methods = [m for m in ("collimated", "isotropic", "measured") if m in summary.get("methods", {})]
    parts = []

    def embed(key: str, alt: str, caption: str = "") -> str:
        if key not in images:
            return ""
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        return f"<figure>{_img(images[key].read_bytes(), alt)}{cap}</figure>"

    parts.append("<h2>Albedo under three light models</h2>")
    parts.append(
        "<p>ρ = π·L / E per pixel (<code>measurement.md</code>, last section), solved in least squares "
        "over the lights that see each point, with the same samples for the three light models. "
        "<b>collimated</b>: one direction and one irradiance for the whole object; <b>isotropic point</b>: "
        "E = I₀·cos/d², I₀ the light's total on-axis intensity, from the sources' centroid weighted by "
        "their on-axis intensity; <b>measured</b>: the fitted near-field model.</p>"
    )
    strip = "".join(embed(f"albedo-{m}", f"albedo, {m}", _METHOD_NAMES[m]) for m in methods)
    if strip:
        parts.append(f'<div class="strip wide">{strip}</div>')
        parts.append(
            f"<p class='caption'>Same scale in every image (ρ = {_fmt(summary.get('png_scale'))} is white, "
            "display gamma 2.2); transparent pixels have no albedo (see the reasons below).</p>"
        )
    rows = []
    for m in methods:
        s = summary["methods"][m]
        rows.append(
            [
                _METHOD_NAMES[m],
                str(s.get("valid_points", 0)),
                _fmt(s.get("median")),
                _fmt(s.get("median_mean")),
                _fmt(s.get("q25")) + " – " + _fmt(s.get("q75")),
                f"{100 * s['cv']:.2f} %" if s.get("cv") is not None else "—",
                f"{100 * s['robust_cv']:.2f} %" if s.get("robust_cv") is not None else "—",
            ]
        )
    parts.append(
        _table(
            [
                "light model",
                "valid points",
                "median ρ (R, G, B)",
                "median ρ (mean of R, G, B)",
                "interquartile range",
                "CV",
                "robust CV (1.4826·MAD/median)",
            ],
            rows,
        )
    )
    parts.append(
        "<p class='caption'>The CV is over every valid point: painted patches of another albedo count as "
        "variation too.</p>"
    )

    parts.append("<h2>Profiles along the object's vertical axis</h2>")
    parts.append(
        embed(
            "profiles",
            "albedo profiles per light model",
            "Median (line) and interquartile range (band) of ρ per height bin, the three light models side "
            "by side (the reference paper's Fig. 11). On an object of uniform albedo the measured model "
            "should be straight; the other two fall off towards the top and bottom, where the light "
            "leaves at larger angles and travels farther.",
        )
        or _note("no profile figure.")
    )

    parts.append("<h2>Which points have an albedo, and why not</h2>")
    parts.append(embed("reasons", "reason code per pixel"))
    counts = summary.get("pixel_reasons", {})
    body = "".join(
        f"<tr><td>{_swatch(PIXEL_COLOURS[c])}</td><td>{c}</td><td>{html.escape(PIXEL_SHORT[c])}</td>"
        f"<td>{html.escape(PIXEL_CODES[c])}</td><td>{counts.get(PIXEL_SHORT[c], 0)}</td></tr>"
        for c in PIXEL_CODES
    )
    parts.append(
        "<table><thead><tr><th></th><th>code</th><th>name</th><th>meaning</th><th>superpixels</th></tr>"
        f"</thead><tbody>{body}</tbody></table>"
    )
    samples = summary.get("sample_reasons", {})
    parts.append("<p>Samples (one per light and point on the object, not counting pixels excluded as a whole):</p>")
    parts.append(
        _table(
            ["code", "name", "meaning", "samples"],
            [
                [str(c), SAMPLE_SHORT[c], SAMPLE_CODES[c], str(samples.get(SAMPLE_SHORT[c], 0))]
                for c in SAMPLE_CODES
                if SAMPLE_SHORT[c] in samples
            ],
        )
    )

    textures = "".join(embed(f"texture-{m}", f"UV texture, {m}", _METHOD_NAMES[m]) for m in methods)
    if textures:
        parts.append("<h2>Albedo in the mesh's UV space</h2>")
        parts.append(f'<div class="strip wide">{textures}</div>')

    parts.append("<h2>Light positions</h2>")
    rows = []
    for light in summary.get("light_positions", []):
        col = light.get("collimated", {})
        rows.append(
            [
                str(light["index"]),
                _fmt([1e3 * v for v in light["position_m"]]),
                _fmt([1e3 * v for v in light["isotropic_point_m"]]),
                _fmt(light.get("I0")),
                _fmt(col.get("direction")),
                _fmt(col.get("E0")),
                _fmt(1e3 * col["distance_m"]) if "distance_m" in col else "—",
            ]
        )
    parts.append(
        _table(
            [
                "light",
                "position [mm]",
                "isotropic point [mm]",
                "I₀ (Σ on-axis)",
                "collimated ω₀",
                "E₀ = I₀/d₀²",
                "d₀ [mm]",
            ],
            rows,
        )
    )
    settings = summary.get("settings", {})
    if settings:
        parts.append("<p>Thresholds:</p>")
        parts.append(_table(None, [[k, _fmt(v)] for k, v in settings.items()]))
    return "\n".join(p for p in parts if p)


def write_reflectance_report(path, summary: dict, *, images: dict | None = None) -> Path:
    """Write the reflectance report: one self-contained HTML page (figures embedded).

    Parameters
    ----------
    path : path-like
        The HTML file to write.
    summary : dict
        The ``reflectance.json`` summary (:func:`processing.reflectance.write_outputs`).
    images : dict, optional
        PNGs to embed (:func:`reflectance_section`).

    Returns
    -------
    Path
    """
    path = Path(path)
    run_id = summary.get("run_id", "")
    title = f"mirrorgonio reflectance: {run_id}" if run_id else "mirrorgonio reflectance"
    rows = [
        [k + ":", str(summary[key])]
        for k, key in (
            ("object run", "object_run"),
            ("rig", "rig"),
            ("mesh", "mesh"),
            ("light model", "light_model"),
            ("light run", "light_run_id"),
            ("light model units", "light_units"),
        )
        if summary.get(key)
    ]
    rows.append(
        [
            "superpixels on the object:",
            f"{summary.get('on_object', 0)} of "
            f"{'×'.join(str(v) for v in summary.get('superpixels', []))}, {summary.get('valid', 0)} with an albedo",
        ]
    )
    rows.append(["light positions:", str(summary.get("lights", ""))])
    rows.append(["generated:", datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")])
    body = [f"<h1>{html.escape(title)}</h1>", _table(None, rows)]
    body.extend(_note(w) for w in summary.get("warnings", []))
    try:
        body.append(reflectance_section(summary, images))
    except Exception as exc:  # noqa: BLE001 - a figure never stops the processing
        log.warning("reflectance report: %s", exc, exc_info=True)
        body.append(_note(f"the reflectance section could not be drawn: {type(exc).__name__}: {exc}"))
    css = _CSS + ".strip.wide img { width: 360px; }\n"
    page = (
        f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{html.escape(title)}</title>\n'
        f"<style>{css}</style>\n</head>\n<body>\n" + "\n".join(body) + "\n</body>\n</html>\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(path)
    return path

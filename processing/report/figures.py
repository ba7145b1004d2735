"""The light report's figures: intensity polar plots, the layout, the θ coverage, the angles, the residuals."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import cast

import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.container import ErrorbarContainer
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Polygon
from matplotlib.ticker import MaxNLocator
from numpy.typing import ArrayLike

from processing.lightmodel import LightModel, SourceModel
from processing.report.context import (
    ReportContext,
    SampleColumns,
    SourceData,
    Truth,
    in_degrees,
    report_context,
    signed_theta,
    truth_values,
)
from processing.report.drawing import COLOURS, add_line, axes_in, grown_runs, new_figure, panel_grid, settle_axes
from processing.trace import ChiefRays

log = logging.getLogger("mirrorgonio.processing")

#: What a panel's legend shows: a line, or the samples' markers with their error bars.
Handle = Line2D | ErrorbarContainer


def fit_curve(source: SourceModel, signed_theta: np.ndarray, azimuth: float) -> tuple[np.ndarray, np.ndarray]:
    theta = np.abs(signed_theta)
    phi = np.where(signed_theta >= 0.0, azimuth, azimuth + math.pi)
    values, extrapolated = source.fit.evaluate(theta, phi)
    values = np.where(theta <= 0.5 * math.pi, np.maximum(values, 0.0), 0.0)
    return values, extrapolated


def _polar_frame(ax: Axes, rmax: float, clip: Polygon) -> None:
    """The half disc's grid, drawn by hand: spokes every 30°, arcs at round radii, their labels."""
    arc = np.radians(np.linspace(-90.0, 90.0, 181))
    ticks = cast(np.ndarray, MaxNLocator(nbins=6, steps=[1, 2, 2.5, 5, 10]).tick_values(0.0, rmax))  # an array
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


def _polar_panel(ax: Axes, ctx: ReportContext, k: int) -> list[Handle]:
    """One source's half-polar plot, drawn on a Cartesian axes whose unit is the radial scale's top
    (θ from the vertical, signed by side: x = r sin θ, y = r cos θ); returns the legend handles it drew."""
    source, d, colour = ctx.model.sources[k], ctx.data[k], ctx.colours[k]
    grid = np.radians(np.linspace(-90.0, 90.0, 721))
    fit, extrapolated = fit_curve(source, grid, ctx.azimuth)
    signed = signed_theta(d.theta, d.phi, ctx.azimuth)
    true = truth_values(ctx.truth, k, source.name, np.abs(grid))
    sigma = np.where(np.isfinite(d.sigma), d.sigma, 0.0)
    # the radial scale: what the data, the covered fit and the truth reach (an extrapolation may run away)
    reach = [d.intensity + sigma, fit[~extrapolated] if np.any(~extrapolated) else fit[np.abs(grid) < 1.4]]
    reach += [a for a in (d.cell_sum, true) if a is not None]
    finite = np.concatenate([np.ravel(a)[np.isfinite(np.ravel(a))] for a in reach])
    rmax = 1.12 * max(float(finite.max()) if finite.size else 0.0, 1e-30)
    rim = np.radians(np.linspace(-90.0, 90.0, 181))
    clip = Polygon(
        np.column_stack([np.sin(rim), np.cos(rim)]), closed=True, facecolor="none", edgecolor="k", lw=0.8, zorder=2.5
    )
    _polar_frame(ax, rmax, clip)
    drawn = _coverage_wedges(ax, signed)
    handles = _curves(ax, grid, fit, extrapolated, true, rmax, colour)
    handles += _sample_markers(ax, d, signed, sigma, rmax, colour, drawn)
    drawn += [h for h in handles if not isinstance(h, ErrorbarContainer)]
    for artist in drawn:
        artist.set_clip_path(clip)
    return handles


def _polar_xy(theta: np.ndarray, r: ArrayLike, rmax: float) -> tuple[np.ndarray, np.ndarray]:
    """A point at angle ``theta`` from the vertical and radius ``r``, in the panel's unit."""
    r = np.asarray(r, dtype=float) / rmax
    return r * np.sin(theta), r * np.cos(theta)


def _coverage_wedges(ax: Axes, signed: np.ndarray) -> list[Artist]:
    """The θ the samples cover, side by side, as grey wedges."""
    drawn: list[Artist] = []
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
    return drawn


def _curves(
    ax: Axes,
    grid: np.ndarray,
    fit: np.ndarray,
    extrapolated: np.ndarray,
    true: np.ndarray | None,
    rmax: float,
    colour: str,
) -> list[Handle]:
    """The fit, solid where the samples cover θ and dashed where it extrapolates, and the truth."""
    sin_grid, cos_grid = np.sin(grid), np.cos(grid)
    shown = np.where(fit <= 1.05 * rmax, fit, np.nan) / rmax
    solid = np.where(~extrapolated, shown, np.nan)
    dashed = np.where(grown_runs(extrapolated), shown, np.nan)
    handles: list[Handle] = [
        add_line(ax, solid * sin_grid, solid * cos_grid, color=colour, lw=2.0, label="fit (θ covered)"),
        add_line(
            ax,
            dashed * sin_grid,
            dashed * cos_grid,
            color=colour,
            lw=1.4,
            ls="--",
            alpha=0.45,
            label="fit, extrapolated",
        ),
    ]
    if true is not None:
        r = np.where(true <= 1.05 * rmax, true, np.nan) / rmax
        handles.append(add_line(ax, r * sin_grid, r * cos_grid, color="k", lw=1.2, ls=(0, (6, 3)), label="truth"))
    return handles


def _sample_markers(
    ax: Axes,
    d: SourceData,
    signed: np.ndarray,
    sigma: np.ndarray,
    rmax: float,
    colour: str,
    drawn: list[Artist],
) -> list[Handle]:
    """The chief-ray cell sums (where they are not the samples themselves) and the samples with
    their ±1σ bars along the radius (the bars are added to ``drawn``, to be clipped)."""
    handles: list[Handle] = []
    if (
        d.cell_sum is not None
        and np.any(np.isfinite(d.cell_sum))
        and not np.allclose(d.cell_sum, d.intensity, equal_nan=True)
    ):
        handles.append(
            add_line(
                ax,
                *_polar_xy(signed, d.cell_sum, rmax),
                ls="none",
                marker="^",
                ms=4,
                mfc="none",
                mec="0.35",
                mew=0.8,
                label="chief-ray cell sums",
            )
        )
    if not d.intensity.size:
        return handles
    has_sigma = bool(np.any(np.isfinite(d.sigma) & (d.sigma > 0)))
    bars: tuple[LineCollection, ...] = ()
    if has_sigma:
        ends = np.stack(
            [
                np.column_stack(_polar_xy(signed, np.maximum(d.intensity - sigma, 0.0), rmax)),
                np.column_stack(_polar_xy(signed, d.intensity + sigma, rmax)),
            ],
            axis=1,
        )
        segments = LineCollection(ends, colors=colour, linewidths=0.9)  # type: ignore[arg-type]  # stubs: an array is accepted
        bars = (cast(LineCollection, ax.add_artist(segments)),)  # add_artist returns the artist it adds
        drawn += bars
    line = add_line(
        ax,
        *_polar_xy(signed, d.intensity, rmax),
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
    return handles


def polar_figure(model: LightModel, *, samples: SampleColumns | None = None, truth: Truth | None = None) -> Figure:
    """Per source, the radiant intensity ``I_s(θ)`` on a half-polar plot (θ from −90° to 90°).

    Dots: the samples with ±1σ bars; solid line: the fit over the θ its samples cover,
    dashed where it extrapolates; open triangles: the chief-ray cell sums of the same
    positions (when the estimator was not the cell sums themselves); broken black line:
    the truth, when ``truth`` is given; grey wedges: the θ the samples cover on each side.

    Each half disc is drawn by hand on a Cartesian axes (matplotlib's polar axes cost
    several times as much to make and draw) whose unit length is the top of its radial
    scale: a sample at signed angle θ and intensity I sits at ``(I sin θ, I cos θ) / I_top``.
    """
    ctx = report_context(model, samples=samples, truth=truth)
    return context_polar_figure(ctx)


def context_polar_figure(ctx: ReportContext) -> Figure:
    n = len(ctx.model.sources)
    rows, cols = panel_grid(n)
    cell_w, cell_h, radius = 4.2, 2.6, 1.65  # inches: a cell, and the radius of its half disc
    top_band, legend_band = 0.3, 0.45
    pad_x, pad_bottom, pad_top = 0.45, 0.3, 0.3  # around the half disc, for its labels
    width, height = cell_w * cols, top_band + cell_h * rows + legend_band
    fig = new_figure(width, height, layout=None)
    handles: dict[object, Handle] = {}  # by label
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
    fig.legend(  # type: ignore[call-overload]  # stubs: containers are handles too, labels any object
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


def layout_figure(
    model: LightModel, *, resolution_m: float = float("nan"), pixel_polygon: np.ndarray | None = None
) -> Figure:
    """The sources on the light plane (circles of their radius) and, drawn to scale, the
    footprint of one pixel: the point spread's (diameter ``resolution_m``) and, when known,
    the chief ray's own (``pixel_polygon``, (4, 2) metres)."""
    colours = [COLOURS[k % len(COLOURS)] for k in range(len(model.sources))]
    fig = new_figure(6.4, 6.0, layout=None)
    has_footprint = math.isfinite(resolution_m) and resolution_m > 0
    legend_lines = int(has_footprint) + int(pixel_polygon is not None)
    bottom = 0.5 + 0.2 * legend_lines
    side = 6.0 - bottom - 0.1  # a square axes: the limits below span the same in u and v
    ax = axes_in(fig, 0.75, bottom, 6.4 - 0.75 - side, 0.1)
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
    handles: list[Artist] = []
    lo = (centres - radii[:, None]).min(axis=0)
    hi = (centres + radii[:, None]).max(axis=0)
    if has_footprint:
        lo, hi = _footprint_circle(ax, centres.mean(axis=0), 0.5 * resolution_m * 1e3, lo, hi, handles)
    if pixel_polygon is not None:
        lo, hi = _pixel_glyph(ax, pixel_polygon, centres, radii, lo, hi, handles)
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
    settle_axes(ax, xlabel_pad=0.25, ylabel_pad=0.4)
    return fig


def _footprint_circle(
    ax: Axes, centroid: np.ndarray, rad: float, lo: np.ndarray, hi: np.ndarray, handles: list[Artist]
) -> tuple[np.ndarray, np.ndarray]:
    """The point spread's footprint, a dashed circle of radius ``rad`` mm about the sources'
    centroid; the plot's (lo, hi) grown to hold it."""
    label = f"what one pixel gathers light from: the point spread's footprint ({2 * rad:.1f} mm across)"
    circle = Circle(tuple(centroid), rad, fill=False, ls="--", lw=1.4, edgecolor="0.3", label=label)
    handles.append(ax.add_patch(circle))
    return np.minimum(lo, centroid - rad), np.maximum(hi, centroid + rad)


def _pixel_glyph(
    ax: Axes,
    pixel_polygon: ArrayLike,
    centres: np.ndarray,
    radii: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    handles: list[Artist],
) -> tuple[np.ndarray, np.ndarray]:
    """One pixel's chief-ray footprint as a scale glyph in the lower-left corner, clear of the
    sources (its shape and size are the pixel's); the plot's (lo, hi) grown to hold it."""
    poly = np.asarray(pixel_polygon, dtype=float) * 1e3
    poly = poly - poly.min(axis=0)
    size = poly.max(axis=0)
    corner = lo + 0.02 * max(float(np.max(hi - lo)), 1.0)
    clear = np.all(np.hypot(*(centres - (corner + 0.5 * size)).T) > radii + 0.75 * float(np.hypot(*size)))
    poly = poly + (corner if clear else lo - size - 0.05 * max(float(np.max(hi - lo)), 1.0))
    label = f"one pixel's chief-ray footprint ({size[0]:.2f} × {size[1]:.2f} mm), to scale, lower left"
    glyph = Polygon(poly, closed=True, facecolor="0.2", edgecolor="k", lw=0.8, alpha=0.8, zorder=3, label=label)
    handles.append(ax.add_patch(glyph))
    return np.minimum(lo, poly.min(axis=0)), np.maximum(hi, poly.max(axis=0))


def coverage_figure(model: LightModel, *, samples: SampleColumns | None = None) -> Figure:
    """The θ (signed by side) each source was sampled at, against the position index."""
    ctx = report_context(model, samples=samples)
    return context_coverage_figure(ctx, samples)


def context_coverage_figure(ctx: ReportContext, samples: SampleColumns | None = None) -> Figure:
    fig = new_figure(7.6, 3.9, layout=None)
    ax = axes_in(fig, 0.75, 0.5, 0.1, 0.1)
    for k, source in enumerate(ctx.model.sources):
        colour = ctx.colours[k]
        if samples is not None and samples.theta.shape[1] == len(ctx.model.sources):
            pos = np.asarray(samples.positions, dtype=float)
            signed = np.degrees(signed_theta(samples.theta[:, k], samples.phi[:, k], ctx.azimuth))
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
                np.degrees(signed_theta(d.theta, d.phi, ctx.azimuth))[order],
                "o-",
                color=colour,
                ms=3.5,
                lw=0.8,
                label=source.name,
            )
    ax.axhline(0.0, color="0.5", lw=0.6)
    ax.set_xlabel("schedule position")
    ax.set_ylabel(f"θ sampled [°]  (+ towards φ = {in_degrees(ctx.azimuth)})")
    ax.grid(True, color="0.9", lw=0.6)
    ax.legend(fontsize=8, ncols=min(len(ctx.model.sources), 5), loc="best", frameon=False)
    settle_axes(ax, xlabel_pad=0.25, ylabel_pad=0.4)
    return fig


def angles_figure(
    rays: ChiefRays,
    *,
    index: int | None = None,
    centre_m: Sequence[float] = (0.0, 0.0),
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
    fig = new_figure(7.2, 4.6, layout=None)
    valid = rays.valid
    defl, theta = np.degrees(rays.deflection[valid]), np.degrees(rays.theta[valid])
    dist = np.hypot(rays.u[valid] - centre_m[0], rays.v[valid] - centre_m[1]) * 1e3
    near = dist <= light_radius_m * 1e3
    top_margin = 0.75 if ball_half_angle is not None and ball_distance_ratio is not None else 0.35
    ax = axes_in(fig, 0.65, 0.5, 1.15 if np.any(near) else 0.15, top_margin)
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

        def to_view(defl: ArrayLike) -> np.ndarray:
            return np.degrees(np.arcsin(np.clip(np.cos(np.radians(np.asarray(defl, dtype=float)) / 2.0) / k, -1, 1)))

        def to_deflection(view: ArrayLike) -> np.ndarray:
            return np.degrees(2.0 * np.arccos(np.clip(np.sin(np.radians(np.asarray(view, dtype=float))) * k, -1, 1)))

        top = ax.secondary_xaxis("top", functions=(to_view, to_deflection))
        top.set_xlabel("the camera's ray: angle off the ball's centre [°]", fontsize=9)
        top.tick_params(labelsize=8)
    ax.set_xlabel("deflection at the ball: angle between the camera's ray and its reflection [°]")
    ax.set_ylabel("outgoing angle θ at the light plane [°]")
    ax.grid(True, color="0.9", lw=0.6)
    ax.legend(fontsize=8, loc="upper right", markerscale=4, frameon=False)
    settle_axes(ax, xlabel_pad=0.25, ylabel_pad=0.35)
    title = "chief rays across the ball" + (f", position {index}" if index is not None else "")
    if ball_half_angle is not None:
        title += f": the ball spans ±{math.degrees(ball_half_angle):.1f}° of the camera's view"
    fig.suptitle(title, fontsize=10)
    return fig


def residuals_figure(model: LightModel, *, samples: SampleColumns | None = None) -> Figure:
    """Per source, the normalised residuals ``(data − fit)/σ`` against θ (signed by side)."""
    ctx = report_context(model, samples=samples)
    return context_residuals_figure(ctx)


def context_residuals_figure(ctx: ReportContext) -> Figure:
    fig, axes = _source_panels(ctx, "(data − fit) / σ")
    for k, (ax, source) in enumerate(zip(axes, ctx.model.sources, strict=True)):
        d = ctx.data[k]
        signed = np.degrees(signed_theta(d.theta, d.phi, ctx.azimuth))
        with np.errstate(invalid="ignore", divide="ignore"):
            r = (d.intensity - source.fit(d.theta, d.phi)) / d.sigma
        ax.axhspan(-3, 3, color="0.93", lw=0)
        ax.axhspan(-1, 1, color="0.85", lw=0)
        ax.axhline(0, color="0.4", lw=0.7)
        ax.plot(signed, r, "o", color=ctx.colours[k], ms=3.5, mec="k", mew=0.3)
        ax.set_title(f"{source.name}: χ²ᵣ = {source.fit.chi2_reduced:.3g}", fontsize=9, y=1.0)  # y: no overlap search
    for ax in axes:
        settle_axes(ax, xlabel_pad=0.25, ylabel_pad=0.45)
    return fig


def context_band_figure(ctx: ReportContext) -> Figure:
    """Per source, the fit's 1σ band (:meth:`~processing.fit.IntensityFit.band`) and the samples,
    both relative to the fit, in % against θ: the band is a few tenths of a per cent of I, which
    no plot of I itself shows."""
    fig, axes = _source_panels(ctx, "relative to the fit [%]")
    for k, (ax, source) in enumerate(zip(axes, ctx.model.sources, strict=True)):
        d = ctx.data[k]
        signed = np.degrees(signed_theta(d.theta, d.phi, ctx.azimuth))
        order = np.argsort(signed)
        with np.errstate(invalid="ignore", divide="ignore"):
            fit = source.fit(d.theta, d.phi)
            band = 100.0 * source.fit.band(d.theta, d.phi) / fit
            deviation, error = 100.0 * (d.intensity - fit) / fit, 100.0 * d.sigma / fit
        ax.fill_between(signed[order], -band[order], band[order], color=ctx.colours[k], alpha=0.35, lw=0)
        ax.axhline(0, color="0.4", lw=0.7)
        ax.errorbar(signed, deviation, error, fmt="o", color="0.25", ms=2.5, elinewidth=0.6, capsize=0)
        on_axis = float(source.fit.band(0.0) / source.intensity(0.0)) if source.intensity(0.0) > 0 else float("nan")
        ax.set_title(f"{source.name}: ±{100 * on_axis:.2g} % on the axis", fontsize=9, y=1.0)
    for ax in axes:
        settle_axes(ax, xlabel_pad=0.25, ylabel_pad=0.45)
    return fig


def _source_panels(ctx: ReportContext, ylabel: str) -> tuple[Figure, list[Axes]]:
    """One panel a source on a grid, sharing one y scale (read off the left column), θ below."""
    n = len(ctx.model.sources)
    rows, cols = panel_grid(n)
    width, height = 3.6 * cols, 2.4 * rows
    fig = new_figure(width, height, layout=None)
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
    axes: list[Axes] = []
    for k in range(n):
        ax = fig.add_subplot(grid[divmod(k, cols)], sharey=axes[0] if axes else None)
        axes.append(ax)
        ax.grid(True, color="0.9", lw=0.5)
        if k % cols == 0:
            ax.set_ylabel(ylabel)
        if k >= n - cols:
            ax.set_xlabel("θ [°] (signed by side)")
        ax.tick_params(labelsize=8, labelleft=k % cols == 0)
    return fig, axes

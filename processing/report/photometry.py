"""The report's first section: the photometry of the whole light, as a lighting engineer reads it.

A table of the figures (:func:`processing.photometry.summarize`), the zonal flux, the C-plane
polar diagram and the isocandela diagram of the whole light, with the range beyond the
measured θ shaded, and the illuminance at 30 cm from the array of sources next to the
far-field approximation.
"""

from __future__ import annotations

import html
import math
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.projections.polar import PolarAxes
from matplotlib.ticker import MaxNLocator

from processing.lightmodel import LightModel
from processing.options import Extrapolation
from processing.photometry import PLANES, ROOM_INDICES, Photometry, far_field, summarize
from processing.report.drawing import new_figure, settle_axes
from processing.report.markup import FigureEncoder, figure_html, html_table

PHOTOMETRY_TITLE = "Photometry of the whole light"
_PLANE_STYLE = {"C0-C180": ("#d62728", "-"), "C90-C270": ("#1f77b4", "--")}
#: Beyond the measured γ: hatched grey (the sources' own polar plots shade what was covered in plain grey).
_BEYOND: dict[str, Any] = {
    "facecolor": "#f0f0f0",
    "edgecolor": "#b8b8b8",
    "hatch": "///",
    "linewidth": 0.0,
    "zorder": 0,  # under everything
}


def _shade_beyond(ax: PolarAxes, start_deg: float, stop_deg: float, rmax: float, label: str | None) -> None:
    """Hatched grey over the angles ``start..stop`` (degrees on the axes' own angle), out to ``rmax``."""
    arc = np.radians(np.linspace(start_deg, stop_deg, 90))
    ax.fill(
        np.r_[0.0, arc, 0.0],
        np.r_[0.0, np.full(arc.size, rmax), 0.0],
        label=label,
        **_BEYOND,
    )


def _deg(value: float | None) -> str:
    return "—" if value is None else f"{value:.1f}°"


def _cplane_axes(ax: PolarAxes, model: LightModel, summary: Photometry) -> None:
    """The C-plane polar diagram on ``ax``: the far field in the C0–C180 and C90–C270 planes on
    one half disc, γ from nadir (down), C0 and C90 to the right; hatched where the measurement ends."""
    ax.set_theta_zero_location("S")
    ax.set_thetamin(-90.0)
    ax.set_thetamax(90.0)
    gamma = np.linspace(0.0, 90.0, 361)
    rmax = 1.08 * summary.peak[0]
    every = summary.light_theta_max_deg[0]
    beyond = "zero in the light files" if summary.extrapolation == Extrapolation.NONE else "the fits' extrapolation"
    _shade_beyond(ax, every, 90.0, rmax, f"beyond the measured γ ({every:.1f}°): {beyond}")
    _shade_beyond(ax, -90.0, -every, rmax, None)
    angles = np.radians(np.concatenate([-gamma[::-1], gamma]))
    for right, left in PLANES:
        plane = f"{right}-{left}"
        colour, style = _PLANE_STYLE[plane]
        c_right, c_left = (np.radians(-float(c[1:])) for c in (right, left))
        values = np.concatenate(
            [
                far_field(model, np.radians(gamma[::-1]), c_left, summary.extrapolation),
                far_field(model, np.radians(gamma), c_right, summary.extrapolation),
            ]
        )
        text = f"{plane}: beam {_deg(summary.angle('beam', plane))}, field {_deg(summary.angle('field', plane))}"
        ax.plot(angles, values, color=colour, ls=style, lw=1.8, label=text)
    ax.set_rmax(rmax)
    ax.set_rticks([t for t in MaxNLocator(4).tick_values(0.0, rmax) if 0.0 < t < rmax])
    ax.set_rlabel_position(-90.0)
    ax.tick_params(labelsize=7)
    ax.set_thetagrids(np.arange(-90, 91, 15), [f"{abs(a)}°" for a in range(-90, 91, 15)])
    ax.text(math.radians(80), 0.62 * rmax, "C0 / C90 →", ha="center", va="center", fontsize=8, color="0.3")
    ax.text(math.radians(-80), 0.62 * rmax, "← C180 / C270", ha="center", va="center", fontsize=8, color="0.3")


def _isocandela_axes(ax: PolarAxes, model: LightModel, summary: Photometry) -> None:
    """The isocandela diagram on ``ax``: lines of equal intensity (10 % … 90 % of the peak) over
    the directions in front of the light, C as the angle (C0 right, C90 up) and γ as the radius;
    the beam (50 %) and field (10 %) lines bold; hatched beyond the measured γ."""
    gamma = np.linspace(0.0, 90.0, 181)
    c = np.linspace(0.0, 360.0, 145)
    table = far_field(model, np.radians(gamma)[None, :], np.radians(-c)[:, None], summary.extrapolation)
    relative = table / summary.peak[0]
    every = summary.light_theta_max_deg[0]
    ax.bar(
        math.pi,
        90.0 - every,
        width=2.0 * math.pi,
        bottom=every,
        **_BEYOND,
    )
    lines = ax.contour(np.radians(c), gamma, relative.T, levels=[0.2, 0.3, 0.4, 0.6, 0.7, 0.8, 0.9], colors="0.25")
    bold = ax.contour(np.radians(c), gamma, relative.T, levels=[0.1, 0.5], colors=["#1f77b4", "#d62728"])
    for contour, width in ((lines, 0.7), (bold, 1.8)):
        contour.set_linewidth(width)
        ax.clabel(contour, fmt=lambda v: f"{100 * v:.0f}%", fontsize=7)
    ax.set_rmax(90.0)
    ax.set_rticks([30, 60, 90])
    ax.set_rlabel_position(67.5)
    ax.set_yticklabels(["γ 30°", "γ 60°", "γ 90°"], fontsize=7)
    ax.set_thetagrids(np.arange(0, 360, 45), [f"C{a}" for a in range(0, 360, 45)], fontsize=8)
    ax.set_title("isocandela diagram, % of the peak (red 50 %, blue 10 %)", fontsize=10, pad=14)


def diagrams_figure(model: LightModel, summary: Photometry) -> Figure:
    """The C-plane polar diagram and the isocandela diagram of the whole light, side by side."""
    fig = new_figure(11.4, 4.8, layout=None)
    left = fig.add_axes((0.02, 0.14, 0.46, 0.88), projection="polar")
    right = fig.add_axes((0.6, 0.06, 0.36, 0.8), projection="polar")
    assert isinstance(left, PolarAxes) and isinstance(right, PolarAxes)
    _cplane_axes(left, model, summary)
    _isocandela_axes(right, model, summary)
    fig.legend(loc="lower left", bbox_to_anchor=(0.05, 0.02), fontsize=8, frameon=False)
    fig.text(0.25, 0.99, f"C-plane polar diagram, I [{model.units}]", ha="center", va="top", fontsize=10)
    return fig


def illuminance_figure(model: LightModel, summary: Photometry) -> Figure:
    """The illuminance on the plane at 30 cm: from the array of sources, from one point
    source at the light's centre, and their difference in % of the peak."""
    near = summary.near
    assert near is not None
    fig = new_figure(12.0, 3.9, layout=None)
    extent = (1e2 * near.x_m[0], 1e2 * near.x_m[-1], 1e2 * near.y_m[0], 1e2 * near.y_m[-1])
    top = float(np.max(near.array))
    difference = near.difference_percent()
    limit = max(float(np.max(np.abs(difference))), 1e-3)
    units = {"W/sr": "W/m²"}.get(model.units, "relative")
    panels = (
        ("array of point sources (the light model)", near.array, "viridis", (0.0, top), f"E [{units}]"),
        ("one point source at the centre (far field)", near.point, "viridis", (0.0, top), f"E [{units}]"),
        ("point − array, % of the peak", difference, "RdBu_r", (-limit, limit), "%"),
    )
    for k, (title, data, cmap, (lo, hi), label) in enumerate(panels):
        ax: Axes = fig.add_axes((0.045 + k * 0.33, 0.13, 0.22, 0.72))
        image = ax.imshow(
            data, origin="lower", extent=extent, cmap=cmap, vmin=lo, vmax=hi, aspect="equal", interpolation="nearest"
        )
        ax.set_title(title, fontsize=9, y=1.0)  # y: no search for what the title overlaps
        ax.set_xlabel("x [cm]", fontsize=8)
        if k == 0:
            ax.set_ylabel("y [cm]", fontsize=8)
        ax.tick_params(labelsize=7)
        settle_axes(ax, xlabel_pad=0.3, ylabel_pad=0.4)
        cax = fig.add_axes((0.27 + k * 0.33, 0.13, 0.012, 0.72))
        bar = fig.colorbar(image, cax=cax)
        bar.set_ticks([t for t in MaxNLocator(5).tick_values(lo, hi) if lo <= t <= hi])
        bar.set_label(label, fontsize=8)
        cax.tick_params(labelsize=7)
    fig.text(
        0.5,
        0.98,
        f"illuminance on a plane {1e2 * near.distance_m:.0f} cm in front of the light, facing it",
        ha="center",
        va="top",
        fontsize=10,
    )
    return fig


def _figures_table(model: LightModel, summary: Photometry) -> str:
    record = summary.record()
    flux_units = record["flux_units"]
    every, some = summary.light_theta_max_deg
    reach = f"{every:.1f}°" if some - every < 0.05 else f"{every:.1f}° (every source; {some:.1f}° some)"
    intensity, gamma, c, symmetric = summary.peak
    rows = [
        [
            "total flux",
            f"{summary.total_flux:.5g} {flux_units}" + (" (model units × sr)" if flux_units == "relative" else ""),
        ],
        ["measured γ range", f"0 – {reach}"],
        [
            "flux beyond the measured γ",
            f"{100 * summary.beyond_fraction:.1f} %"
            + (
                f" (zero in the light files; the fits would put {100 * summary.fitted_beyond_fraction:.1f} % there)"
                if summary.extrapolation == Extrapolation.NONE
                else " (the fits' extrapolation, as written in the light files)"
            ),
        ],
        [
            "peak intensity",
            f"{intensity:.5g} {model.units} at γ {gamma:.1f}°, " + ("any C" if symmetric else f"C {c:.1f}°"),
        ],
    ]
    for kind, share in (("beam", "50 %"), ("field", "10 %")):
        for plane, angles in summary.angles[kind].items():
            halves = ", ".join(f"{half} {_deg(v)}" for half, v in angles.half_angles_deg.items())
            note = " — rests on the extrapolation beyond the measured γ" if angles.beyond_measured else ""
            rows.append([f"{kind} angle ({share} of peak), {plane}", f"{_deg(angles.angle_deg)} ({halves}){note}"])
    if summary.direct_ratios:
        rows.append(
            [
                "direct ratios (LDT), room index k " + " / ".join(f"{k:g}" for k in ROOM_INDICES),
                " / ".join(f"{r:.3f}" for r in summary.direct_ratios)
                + " (share of the flux falling directly on the work plane; square room, luminaires spread "
                "evenly over the ceiling)",
            ]
        )
    near = record.get("near_field")
    if near is not None:
        rows.append(
            [
                f"illuminance at {1e2 * near['distance_m']:.0f} cm, peak",
                f"{near['peak_illuminance_array']:.5g} {near['illuminance_units']} from the array of sources, "
                f"{near['peak_illuminance_point']:.5g} from one point source at the centre",
            ]
        )
        rows.append(
            [
                "far-field approximation at that distance",
                f"largest difference {near['max_difference_percent_of_peak']:.2f} % of the peak illuminance; "
                f"{near['max_difference_percent_in_field']:.2f} % locally where E ≥ 10 % of the peak",
            ]
        )
    return html_table(["figure", "value"], rows)


def _zones_table(summary: Photometry) -> str:
    rows = [
        [
            f"{z['gamma_deg'][0]}–{z['gamma_deg'][1]}°",
            f"{z['flux']:.4g}",
            f"{z['percent']:.1f}",
            f"{z['cumulative_percent']:.1f}",
            f"{z['beyond_measured_percent']:.0f}",
        ]
        for z in summary.record()["zones"]
    ]
    return html_table(["zone γ", "flux", "% of total", "cumulative %", "% of the zone beyond the measured γ"], rows)


def _absolute_html(absolute: dict[str, Any]) -> str:
    """The light in candela and lumens (``photometry.absolute``): where the scale comes from and
    each source's peak and flux with their 1σ."""
    calibration = absolute["calibration"]
    rescaled = calibration["rescaled_by"]
    said = (
        f"<p><b>Absolute photometry.</b> The camera's photometric scale, {calibration['candela_per_unit']:.6g} cd "
        f"per unit ± {100 * calibration['relative_uncertainty']:.2f} % (1σ), read from "
        f"{html.escape(str(calibration['from']))}: {html.escape(str(calibration['reference']))}"
        + (
            f", rescaled by {rescaled:.6g} for the camera's gain and sensitivity as now described"
            if rescaled != 1.0
            else ""
        )
        + f". Across colours: {html.escape(absolute['colour'])}. Total luminous flux "
        f"<b>{absolute['flux_lm']:.5g} lm ± {absolute['flux_lm_sigma']:.2g}</b> (1σ); the IES, LDT, TM-25 and "
        "pbrt files are in candela and lumens.</p>"
    )
    rows = [
        [
            entry["name"],
            f"{entry['candela_per_unit']:.6g}",
            f"{entry['peak_cd']:.5g} ± {entry['peak_cd_sigma']:.2g} at θ {entry['peak_theta_deg']:.1f}°",
            f"{entry['flux_lm']:.5g}",
            f"{100 * entry['relative_uncertainty']:.2f} % (of which colour {100 * entry['spectral_mismatch']:.2f} %)",
        ]
        for entry in absolute["sources"]
    ]
    return said + html_table(["source", "cd per unit", "peak (cd, 1σ)", "flux (lm)", "scale's 1σ"], rows)


def photometry_section(model: LightModel, encoder: FigureEncoder | None = None) -> str:
    """The section's HTML: the figures, the zonal flux, the two diagrams and the illuminance maps,
    for the extrapolation the light files were written with (the model's ``photometry``)."""
    summary = summarize(model, model.photometry.get("extrapolation", Extrapolation.FITTED))
    every = summary.light_theta_max_deg[0]
    written = "zero" if summary.extrapolation == Extrapolation.NONE else "the fits' extrapolation"
    units = (
        "in W/sr"
        if model.units == "W/sr"
        else "relative (in candela below)"
        if "absolute" in model.photometry
        else "relative (not calibrated)"
    )
    parts = [
        f"<p>The whole light, as its IES and LDT files describe it: beyond the measured γ ({every:.1f}°) they "
        f"hold {html.escape(written)} (<code>--extrapolation</code>). Intensities {units}; "
        "γ from the light's axis, C counter-clockwise from the light's +x seen from the lit side.</p>",
        _figures_table(model, summary),
        *([_absolute_html(model.photometry["absolute"])] if "absolute" in model.photometry else []),
        figure_html(
            diagrams_figure(model, summary),
            "C-plane polar diagram and isocandela diagram",
            "Left: the C-plane polar diagram, the intensity in the C0–C180 (solid) and C90–C270 (dashed) planes, γ "
            "from the light's axis (down). Right: the isocandela diagram, C as the angle and γ as the radius. Hatched: "
            "beyond the γ the sweep measured.",
            encoder,
        ),
        figure_html(
            illuminance_figure(model, summary),
            "illuminance at 30 cm",
            "Illuminance at 30 cm: each source an inverse-square point at its place (the light model), against one "
            "point source of the whole far field at the centre of the luminous opening (what a lighting program does "
            "with the IES file), and the difference.",
            encoder,
        ),
        "<p>Flux by zone of γ:</p>",
        _zones_table(summary),
    ]
    return "\n".join(parts)

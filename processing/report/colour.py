"""The report's colour section: each source's and the whole light's chromaticity, CCT and Duv
(:mod:`processing.colour`), and their colour over θ where it varies."""

from __future__ import annotations

import html
from typing import Any

from matplotlib.figure import Figure

from processing.colour import VARIES_UV
from processing.lightmodel import LightModel
from processing.report.drawing import COLOURS, axes_in, new_figure, settle_axes
from processing.report.markup import FigureEncoder, figure_html, html_note, html_table

TITLE = "The light's colour"


def _number(value: Any, fmt: str) -> str:
    return format(value, fmt) if isinstance(value, (int, float)) else "—"


def _row(name: str, section: dict[str, Any]) -> list[str]:
    rgb = section.get("camera_rgb") or [float("nan")] * 3
    cct = section.get("cct_k")
    over = section.get("over_theta") or {}
    if "max_delta_uv" in over:
        spread = f"{over['max_delta_uv']:.4f}"
    else:
        spread = "—"
    return [
        name,
        " / ".join(f"{v:.3f}" for v in rgb),
        _number(section.get("x"), ".4f"),
        _number(section.get("y"), ".4f"),
        _number(section.get("u_prime"), ".4f"),
        _number(section.get("v_prime"), ".4f"),
        f"{cct:.0f} K" if isinstance(cct, (int, float)) else ("|Duv| > 0.05: none" if "duv" in section else "—"),
        _number(section.get("duv"), "+.4f"),
        spread,
    ]


def colour_figure(model: LightModel) -> Figure:
    """CCT (top) and Duv (bottom) of each source and of the whole light against θ, one point per
    bin of θ."""
    fig = new_figure(7.6, 4.6, layout=None)
    top = axes_in(fig, 0.85, 2.55, 0.1, 0.1)
    bottom = axes_in(fig, 0.85, 0.5, 0.1, 2.35, sharex=top)
    lines = [
        (s.name, s.chromaticity.get("over_theta") or {}, COLOURS[k % len(COLOURS)], "o-", 0.8)
        for k, s in enumerate(model.sources)
    ]
    lines.append(("whole light", model.chromaticity.get("over_theta") or {}, "black", "s-", 1.6))
    for name, over, colour, style, width in lines:
        theta, cct, duv = over.get("theta_deg", []), over.get("cct_k", []), over.get("duv", [])
        points = [(t, c) for t, c in zip(theta, cct, strict=False) if c is not None]
        if points:
            top.plot(*zip(*points, strict=True), style, color=colour, ms=3.5, lw=width, label=name)
        points = [(t, d) for t, d in zip(theta, duv, strict=False) if d is not None]
        if points:
            bottom.plot(*zip(*points, strict=True), style, color=colour, ms=3.5, lw=width)
    top.set_ylabel("CCT [K]")
    bottom.set_ylabel("Duv")
    bottom.set_xlabel("θ from the light's axis [°]")
    for ax in (top, bottom):
        ax.grid(True, color="0.9", lw=0.6)
    top.tick_params(labelbottom=False)
    top.legend(fontsize=8, ncols=min(len(model.sources) + 1, 6), loc="best", frameon=False)
    settle_axes(top, xlabel_pad=None, ylabel_pad=0.7)
    settle_axes(bottom, xlabel_pad=0.3, ylabel_pad=0.7)
    return fig


def _bin_deg(model: LightModel) -> float:
    for over in [s.chromaticity.get("over_theta") or {} for s in model.sources] + [
        model.chromaticity.get("over_theta") or {}
    ]:
        if "bin_deg" in over:
            return float(over["bin_deg"])
    return 5.0


def colour_section(model: LightModel, encoder: FigureEncoder | None = None) -> str:
    """The section's HTML: a table of every source and the whole light, what the numbers rest
    on, and the figure over θ where a source's colour varies by more than
    :data:`processing.colour.VARIES_UV` in u'v'."""
    sections = [(s.name, s.chromaticity) for s in model.sources if s.chromaticity]
    if not sections:
        return html_note(
            "no colour was measured: the sources' channels were not estimated apart (cell sums), or the "
            "model predates colour"
        )
    if model.chromaticity:
        sections.append(("whole light", model.chromaticity))
    header = ["source", "camera R / G / B", "x", "y", "u′", "v′", "CCT", "Duv", "max Δu′v′ over θ"]
    parts = [html_table(header, [_row(name, section) for name, section in sections])]
    basis = sections[0][1].get("basis", "")
    text = (
        f"Colour in {basis}. x, y: CIE 1931 chromaticity; u′, v′: CIE 1976 UCS; CCT and Duv: Ohno (2013), "
        "none where the light lies farther than 0.05 from the Planckian locus; camera R / G / B: the "
        "channels' intensities relative to their mean. The whole light weighs each source by its flux. "
        "A camera of three channels gives no colour rendering index (it needs the spectrum). "
    )
    if not any("x" in section for _, section in sections):
        text = (
            "The run file holds no colour matrices for its camera, so the colour is camera RGB only (no "
            "chromaticity, CCT or Duv): the camera's raw files carried none, or the run file predates them."
        )
    parts.append(f"<p>{html.escape(text)}</p>")
    varying = [s.name for s in model.sources if (s.chromaticity.get("over_theta") or {}).get("varies", False)]
    if (model.chromaticity.get("over_theta") or {}).get("varies", False):
        varying.append("the whole light")
    if varying:
        caption = (
            f"CCT and Duv of each source and of the whole light (black squares) against θ, in bins of "
            f"{_bin_deg(model):g}°: a source's samples' channels summed in the bin (so the strong samples "
            "count most), the whole light's the sources' colours in the bin weighed by their flux in it "
            f"(their fits, up to the largest θ measured). Varying by more than {VARIES_UV} in u′v′: "
            f"{', '.join(varying)}."
        )
        parts.append(figure_html(colour_figure(model), "colour over θ", html.escape(caption), encoder))
    elif any("max_delta_uv" in (s.chromaticity.get("over_theta") or {}) for s in model.sources):
        light = " and the whole light's" if "max_delta_uv" in (model.chromaticity.get("over_theta") or {}) else ""
        parts.append(
            "<p>"
            + html.escape(
                f"Each source's colour{light} is the same over the θ measured to within {VARIES_UV} in u′v′ "
                "(max Δu′v′ over θ above): no plot over θ."
            )
            + "</p>"
        )
    return "\n".join(parts)

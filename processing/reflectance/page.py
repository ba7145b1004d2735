"""The reflectance's report page: the summary, the maps and the profiles along the object."""

from __future__ import annotations

import html
import logging
import math
import os
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from matplotlib.figure import Figure

from processing.reflectance.codes import PIXEL_CODES, PIXEL_COLOURS, PIXEL_SHORT, SAMPLE_CODES, SAMPLE_SHORT
from processing.report.drawing import COLOURS, new_figure
from processing.report.markup import CSS, embedded_img, html_note, html_table, write_page

log = logging.getLogger("mirrorgonio.processing")


class Embed(Protocol):
    """``embed(key, alt, caption)``: the named image as a ``<figure>``, or "" when there is none."""

    def __call__(self, key: str, alt: str, caption: str = "") -> str: ...


_METHOD_NAMES = {"collimated": "collimated", "isotropic": "isotropic point", "measured": "measured near-field model"}


def reflectance_profiles_figure(
    profiles: dict[str, Any], methods: Sequence[str] = ("collimated", "isotropic", "measured")
) -> Figure:
    """ρ along the object's vertical axis, one panel per light model (the reference paper's Fig. 11).

    ``profiles`` is :func:`processing.reflectance.maps.reflectance_profiles`'s dict: per height bin
    the median (line) and the interquartile band (shaded) of the channel mean of ρ. The
    measured model's overall median is drawn in every panel as a dashed line, for scale.
    """
    methods = [m for m in methods if m in profiles]
    fig = new_figure(3.6 * max(len(methods), 1), 4.6)
    axes = fig.subplots(1, max(len(methods), 1), sharex=True, sharey=True, squeeze=False)[0]
    height = 1e3 * np.asarray(profiles.get("height_m", []), dtype=float)
    reference = None
    if "measured" in profiles:
        med = np.asarray(profiles["measured"]["median"], dtype=float)
        counts = np.asarray(profiles["measured"]["count"], dtype=float)
        ok = np.isfinite(med)
        if ok.any():
            reference = float(np.average(med[ok], weights=counts[ok]))
    for ax, m, colour in zip(axes, methods, COLOURS, strict=False):
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


def _swatch(rgb: Iterable[float]) -> str:
    r, g, b = (int(c) for c in rgb)
    return (
        f'<span style="display:inline-block;width:1.2em;height:1em;border:1px solid #888;'
        f'background:rgb({r},{g},{b})"></span>'
    )


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "—"
    if isinstance(value, (list, tuple)):
        return ", ".join(_fmt(v, digits) for v in value)
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    return f"{v:.{digits}g}" if math.isfinite(v) else "—"


def reflectance_section(summary: dict[str, Any], images: dict[str, Path] | None = None) -> str:
    """The reflectance results as an HTML fragment (headings ``<h2>`` and below).

    Parameters
    ----------
    summary : dict
        The ``reflectance.json`` summary (:func:`processing.reflectance.outputs.write_outputs`).
    images : dict of str to path-like, optional
        PNG files embedded: ``albedo-<method>``, ``reasons``, ``profiles`` and
        ``texture-<method>``.
    """

    images = {k: Path(v) for k, v in (images or {}).items() if v is not None and Path(v).is_file()}
    methods = [m for m in ("collimated", "isotropic", "measured") if m in summary.get("methods", {})]

    def embed(key: str, alt: str, caption: str = "") -> str:
        if key not in images:
            return ""
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        return f"<figure>{embedded_img(images[key].read_bytes(), alt)}{cap}</figure>"

    parts = [
        *_albedo_part(summary, methods, embed),
        *_profiles_part(embed),
        *_reasons_part(summary, embed),
        *_textures_part(methods, embed),
        *_brdf_part(summary, methods, embed),
        *_lights_part(summary),
    ]
    return "\n".join(p for p in parts if p)


def _albedo_part(summary: dict[str, Any], methods: list[str], embed: Embed) -> list[str]:
    """The albedo maps under the three light models and their statistics."""
    parts = [
        "<h2>Albedo under three light models</h2>",
        "<p>ρ = π·L / E per pixel (<code>docs/measurement.md</code>, diffuse reflectance under near light), "
        "solved in least squares "
        "over the lights that see each point, with the same samples for the three light models. "
        "<b>collimated</b>: one direction and one irradiance for the whole object; <b>isotropic point</b>: "
        "E = I₀·cos/d², I₀ the light's total on-axis intensity, from the sources' centroid weighted by "
        "their on-axis intensity; <b>measured</b>: the fitted near-field model.</p>",
    ]
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
    header = [
        "light model",
        "valid points",
        "median ρ (R, G, B)",
        "median ρ (mean of R, G, B)",
        "interquartile range",
        "CV",
        "robust CV (1.4826·MAD/median)",
    ]
    parts.append(html_table(header, rows))
    parts.append(
        "<p class='caption'>The CV is over every valid point: painted patches of another albedo count as "
        "variation too.</p>"
    )
    return parts


def _profiles_part(embed: Embed) -> list[str]:
    """The profiles of ρ along the object's vertical axis."""
    figure = embed(
        "profiles",
        "albedo profiles per light model",
        "Median (line) and interquartile range (band) of ρ per height bin, the three light models side "
        "by side (the reference paper's Fig. 11). On an object of uniform albedo the measured model "
        "should be straight; the other two fall off towards the top and bottom, where the light "
        "leaves at larger angles and travels farther.",
    )
    return ["<h2>Profiles along the object's vertical axis</h2>", figure or html_note("no profile figure.")]


def _reasons_part(summary: dict[str, Any], embed: Embed) -> list[str]:
    """The reason map, the pixels and the samples counted per reason code."""
    counts = summary.get("pixel_reasons", {})
    body = "".join(
        f"<tr><td>{_swatch(PIXEL_COLOURS[c])}</td><td>{c}</td><td>{html.escape(PIXEL_SHORT[c])}</td>"
        f"<td>{html.escape(PIXEL_CODES[c])}</td><td>{counts.get(PIXEL_SHORT[c], 0)}</td></tr>"
        for c in PIXEL_CODES
    )
    samples = summary.get("sample_reasons", {})
    sample_rows = [
        [str(c), SAMPLE_SHORT[c], SAMPLE_CODES[c], str(samples.get(SAMPLE_SHORT[c], 0))]
        for c in SAMPLE_CODES
        if SAMPLE_SHORT[c] in samples
    ]
    return [
        "<h2>Which points have an albedo, and why not</h2>",
        embed("reasons", "reason code per pixel"),
        "<table><thead><tr><th></th><th>code</th><th>name</th><th>meaning</th><th>superpixels</th></tr>"
        f"</thead><tbody>{body}</tbody></table>",
        "<p>Samples (one per light and point on the object, not counting pixels excluded as a whole):</p>",
        html_table(["code", "name", "meaning", "samples"], sample_rows),
    ]


def _textures_part(methods: list[str], embed: Embed) -> list[str]:
    """The albedo in the mesh's UV space, where the mesh has UVs."""
    textures = "".join(embed(f"texture-{m}", f"UV texture, {m}", _METHOD_NAMES[m]) for m in methods)
    if not textures:
        return []
    return ["<h2>Albedo in the mesh's UV space</h2>", f'<div class="strip wide">{textures}</div>']


def _brdf_part(summary: dict[str, Any], methods: list[str], embed: Embed) -> list[str]:
    """The whole reflectance: per light model what was fitted, and the relighting check."""
    brdf = summary.get("brdf")
    if not brdf:
        skipped = summary.get("brdf_skipped")
        return ["<h2>The whole reflectance</h2>", html_note(f"not fitted: {skipped}")] if skipped else []
    header = ["light model", "own lobe", "shared", "ρ median (R, G, B)", "F0 median", "α median", "relit RMS"]
    rows = []
    for m in methods:
        stats = brdf["methods"].get(m, {})
        counts = stats.get("confidence", {})
        relit = stats.get("relighting", {})
        rows.append(
            [
                _METHOD_NAMES[m],
                str(counts.get("own", 0)),
                str(counts.get("shared", 0)),
                ", ".join(_fmt(v, 3) for v in stats.get("diffuse_median", [])),
                ", ".join(_fmt(v, 3) for v in stats.get("specular_median", [])),
                _fmt(stats.get("roughness_median"), 3),
                f"{100 * relit['rms_relative']:.1f} %" if "rms_relative" in relit else "—",
            ]
        )
    held = brdf.get("held_out_positions", [])
    strips = "".join(
        embed(f"relit-{j}", f"held-out position {j}", f"position {j}: photograph, rendering, 5 × |difference|")
        for j in held
    )
    maps = "".join(
        embed(f"{kind}-measured", f"{kind}, measured light", caption)
        for kind, caption in (("basecolor", "base colour (glTF)"), ("confidence", "confidence: own, shared, none"))
    )
    novel = embed("relit-novel", "relit under a new light", "the object under a light the run never used")
    return [
        "<h2>The whole reflectance: diffuse, specular, roughness</h2>",
        html_table(header, rows),
        f'<div class="strip wide">{maps}</div>' if maps else "",
        "<h3>Relighting: held-out positions</h3>" if strips else "",
        f'<div class="strip wide">{strips}</div>' if strips else "",
        f'<div class="strip wide">{novel}</div>' if novel else "",
    ]


def _lights_part(summary: dict[str, Any]) -> list[str]:
    """Each light position, what the isotropic and collimated models made of it, the thresholds."""
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
    header = ["light", "position [mm]", "isotropic point [mm]", "I₀ (Σ on-axis)", "collimated ω₀", "E₀ = I₀/d₀²"]
    parts = ["<h2>Light positions</h2>", html_table([*header, "d₀ [mm]"], rows)]
    settings = summary.get("settings", {})
    if settings:
        parts.append("<p>Thresholds:</p>")
        parts.append(html_table(None, [[k, _fmt(v)] for k, v in settings.items()]))
    return parts


def write_reflectance_report(
    path: str | os.PathLike[str], summary: dict[str, Any], *, images: dict[str, Path] | None = None
) -> Path:
    """Write the reflectance report: one self-contained HTML page (figures embedded).

    Parameters
    ----------
    path : path-like
        The HTML file to write.
    summary : dict
        The ``reflectance.json`` summary (:func:`processing.reflectance.outputs.write_outputs`).
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
    body = [f"<h1>{html.escape(title)}</h1>", html_table(None, rows)]
    body.extend(html_note(w) for w in summary.get("warnings", []))
    try:
        body.append(reflectance_section(summary, images))
    except Exception as exc:  # noqa: BLE001 - a figure never stops the processing
        log.warning("reflectance report: %s", exc, exc_info=True)
        body.append(html_note(f"the reflectance section could not be drawn: {type(exc).__name__}: {exc}"))
    css = CSS + ".strip.wide img { width: 360px; }\n"
    return write_page(path, title, body, css)

"""The light report's sections, each a piece of HTML: the header, the figures, the calibration, the previews."""

from __future__ import annotations

import html
import logging
import math
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from drivers.contracts.rig import Rig
from drivers.contracts.runfile import RunFile
from processing.calibration import BallFit, angle_sensitivity, calibrate_ball, compare_with_rig
from processing.lightmodel import LightModel, SourceModel, describe_fitted
from processing.report.context import (
    MiddlePosition,
    ReportContext,
    RunReport,
    SampleColumns,
    in_degrees,
    source_data,
    truth_error,
)
from processing.report.figures import (
    angles_figure,
    context_band_figure,
    context_coverage_figure,
    context_polar_figure,
    context_residuals_figure,
    layout_figure,
)
from processing.report.markup import embedded_img, figure_html, html_note, html_table, in_mm
from processing.report.trust import rig_calibration_part
from processing.results import run_name

log = logging.getLogger("mirrorgonio.processing")


NO_CALIBRATION = "no calibration image in this run"


SECTIONS = (
    "The light source, source by source",
    "The sources on the light plane",
    "Which θ each source was sampled at",
    "How the ball widens the angles",
    "How well the fits describe the samples",
    "Calibration check: the ball's position",
    "HDR frames over the sweep",
)


_PREVIEWS = 6


_PREVIEW_WIDTH = 320


_PREVIEW_CROP = 200


def calibration_section(
    model: LightModel,
    run: RunFile | None,
    report: RunReport | None,
    calibration: BallFit | dict[str, Any] | None,
    geo: MiddlePosition | None,
) -> str:
    rig = run.header.rig if run is not None else None
    found = calibration
    if found is None and report is not None:
        found = getattr(report, "calibration", None)
    if found is None:
        found = model.provenance.get("calibration")
    if found is None and run is not None and callable(getattr(run, "calibration_image", None)):
        image = cast(Any, run).calibration_image()  # a run file that offers one (RunFile has none)
        if image is not None:
            assert rig is not None  # the run's
            found = calibrate_ball(image, rig)
    parts = [rig_calibration_part(model)]
    comparison = None
    if found is None and parts[0]:
        parts.append("<p>No separate measurement of the ball's centre was given (<code>--ball-centre</code>).</p>")
    elif found is None:
        parts.append(html_note(f"{NO_CALIBRATION}: the processing used the ball centre of the rig description."))
    elif isinstance(found, dict):
        comparison = found
    elif rig is not None and hasattr(found, "centre_camera"):
        comparison = compare_with_rig(found, rig)
    else:
        parts.append(html_note("a calibration result is present, but without the run's rig it cannot be compared."))
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
        parts.append(html_table(["ball centre [mm]", "x", "y", "z"], rows))
        distance, significance = comparison.get("distance_mm"), comparison.get("significance")
        if distance is not None:
            text = f"The ball is {float(distance):.3f} mm from where the rig description puts it"
            if significance is not None:
                text += f" ({float(significance):.1f} σ of the measurement)"
            parts.append(f"<p>{html.escape(text)}.</p>")
    if rig is not None and geo is not None:
        parts.extend(_ball_error_costs(rig, geo, comparison))
    return "\n".join(parts)


def _ball_error_costs(rig: Rig, geo: MiddlePosition, comparison: dict[str, Any] | None) -> list[str]:
    """What 1 mm of error in the ball's position costs in θ at the middle position (and at the
    measured discrepancy, where there is one)."""
    out: list[str] = []
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
    out.append(
        f"<p>What 1 mm of error in the ball's position costs, at position {geo.index} "
        f"(chief rays landing within {sens['plane_radius_mm']:.0f} mm of the light's axis):</p>"
    )
    out.append(
        html_table(
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
        out.append(f"<p>At the measured discrepancy that is about {shift:.3f}° of θ (median, worst axis).</p>")
    return out


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


def _previews(report: RunReport | None, run: RunFile | None, model: LightModel, path: Path) -> list[Path]:
    outputs = getattr(report, "outputs", None) or {}
    pngs = [Path(p) for p in outputs.get("png", [])]
    if not pngs:
        stems = []
        if report is not None:
            stems.append(Path(report.results_file).parent / f"{run_name(report.run_file)}.hdr")
        if run is not None:
            stems.append(path.parent / f"{run_name(run.path)}.hdr")
            stems.append(Path(run.path).parent / f"{run_name(run.path)}.hdr")
        if model.provenance.get("run_file"):
            run_file = Path(model.provenance["run_file"])
            stems += [path.parent / f"{run_name(run_file)}.hdr", run_file.parent / f"{run_name(run_file)}.hdr"]
        for folder in stems:
            if folder.is_dir():
                pngs = sorted(folder.glob("position-*.png"))
                if pngs:
                    break
    return [p for p in pngs if p.exists()]


def _ball_box(geo: MiddlePosition | None) -> tuple[float, float, float, int] | None:
    """The ball's image as ``(col, row, radius, sensor width)`` in sensor pixels, to crop the previews."""
    if geo is None:
        return None
    g = geo.geometry
    centre = g.project(g.ball_centre[None, :])[0]
    distance = float(np.linalg.norm(g.ball_centre - g.camera_centre))
    radius = g.K[0, 0] * math.tan(math.asin(min(1.0, g.ball_radius / distance)))
    return float(centre[0]), float(centre[1]), 1.15 * radius, g.width


def _preview_strip(pngs: list[Path], box: tuple[float, float, float, int] | None = None) -> str:

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
        cells.append(
            f"<figure>{embedded_img(encoded.tobytes(), label)}<figcaption>{html.escape(label)}</figcaption></figure>"
        )
    return f'<div class="strip">{"".join(cells)}</div>' if cells else ""


def header_table(
    model: LightModel, run: RunFile | None, report: RunReport | None, samples: SampleColumns | None, resolution_m: float
) -> str:
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
    n = [len(d.theta) for d in source_data(model, samples)]
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
            f"{in_mm(resolution_m)}: the point spread's footprint, the patch of the light plane one pixel "
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
    return html_table(None, [[f"{name}:", value] for name, value in rows])


def intensity_section(ctx: ReportContext) -> str:
    model = ctx.model
    side = f"{in_degrees(ctx.azimuth)}"
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
    parts = [
        figure_html(
            context_polar_figure(ctx), "radiant intensity per source, half-polar", html.escape(caption), ctx.encoder
        )
    ]
    header = [
        "source",
        "(u, v) [mm]",
        "radius [mm]",
        f"on-axis I [{model.units}]",
        "half-width at half max",
        "θ covered",
        "samples",
        "χ²ᵣ",
        "1σ of I on the axis (of which model error)",
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
            _band_on_axis(source),
        ]
        if ctx.truth is not None:
            err = truth_error(source, ctx.truth, k)
            row.append(f"{100 * err:.3g} %" if err is not None else "no truth for this source")
        rows.append(row)
    parts.append(html_table(header, rows))
    if ctx.truth is not None:
        parts.append(
            "<p>Error vs truth: RMS(I<sub>fit</sub> − I<sub>true</sub>) / max(I<sub>true</sub>) over the θ "
            "the source's samples cover (<code>docs/measurement.md</code>).</p>"
        )
    return "\n".join(parts)


def _band_on_axis(source: SourceModel) -> str:
    """The fit's 1σ on the axis (:meth:`~processing.fit.IntensityFit.band`), in % of I there."""
    value, sigma = float(source.intensity(0.0)), float(source.fit.band(0.0))
    if not (value > 0 and math.isfinite(sigma)):
        return "not determined"
    return f"{100 * sigma / value:.2f} % ({100 * float(source.fit.info.get('model_error', 0.0)):.2f} %)"


def layout_section(ctx: ReportContext) -> str:
    polygon = ctx.geometry.pixel_polygon if ctx.geometry is not None else None
    fig = layout_figure(ctx.model, resolution_m=ctx.resolution_m, pixel_polygon=polygon)
    caption = (
        "The sources where the layout puts them on the light plane (circles of their emitting radius), "
        "seen from the front (the light emits towards the viewer). "
    )
    if math.isfinite(ctx.resolution_m):
        caption += (
            f"The dashed circle, drawn to the same scale, is the patch one camera pixel gathers light from "
            f"(the point spread's footprint, {in_mm(ctx.resolution_m)} across): where it covers several "
            f"sources, a pixel mixes them and only the templates' unmixing tells them apart. "
        )
    if polygon is not None:
        assert ctx.geometry is not None and ctx.geometry.pixel_at is not None  # set with the polygon
        caption += (
            f"The small black patch is where one pixel's chief ray alone would look (pixel "
            f"{ctx.geometry.pixel_at[0]:.0f}, {ctx.geometry.pixel_at[1]:.0f} at position "
            f"{ctx.geometry.index}): sharp, but not what the pixel sees."
        )
    parts = [figure_html(fig, "sources on the light plane", html.escape(caption), ctx.encoder)]
    if not math.isfinite(ctx.resolution_m):
        parts.append(html_note("the spatial resolution is not recorded in the light model: no footprint drawn."))
    if polygon is None and ctx.geometry_note:
        parts.append(html_note(f"no chief-ray footprint: {ctx.geometry_note}."))
    return "\n".join(parts)


def coverage_section(ctx: ReportContext, samples: SampleColumns | None) -> str:
    caption = (
        "The angle θ each source's sample leaves at, position by position (signed by side as in the polar "
        "plots). A sweep past the ball draws one line per source crossing 0 near the middle; the gaps "
        "between the lines are the sources' different view of the ball. The fits are valid over the θ "
        "range each line spans."
    )
    if samples is not None:
        caption += " Crosses mark positions where the source was in view but had no estimate."
    return figure_html(
        context_coverage_figure(ctx, samples), "theta sampled per position", html.escape(caption), ctx.encoder
    )


def angles_section(ctx: ReportContext) -> str:
    geo = ctx.geometry
    if geo is None or geo.rays is None:
        return html_note(f"skipped: {ctx.geometry_note or 'no run file'}.")
    rays = geo.rays
    if not np.any(rays.valid):
        return html_note(f"skipped: no chief ray reaches the light plane at position {geo.index}.")
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
    return figure_html(fig, "outgoing angle against deflection", html.escape(caption), ctx.encoder)


def residuals_section(ctx: ReportContext) -> str:
    caption = (
        "Data minus fit at each sample, in units of the sample's σ (dark band ±1σ, light band ±3σ). "
        "A good fit scatters evenly about 0, mostly within the dark band, and has χ²ᵣ near 1; a wave or a "
        "trend with θ means the model's shape does not match the source."
    )
    band = (
        "Each source's 1σ band on I(θ) (shaded; the light model's band: the fit's covariance, the templates' model "
        "error as a scale common to the sweep included) and the samples with their σ, both relative to the fit. "
        "The band is what to propagate from this light; the samples' scatter about it is what the fit left."
    )
    residuals = context_residuals_figure(ctx)
    parts = [
        figure_html(residuals, "normalised residuals per source", html.escape(caption), ctx.encoder),
        figure_html(context_band_figure(ctx), "1σ band on I per source", html.escape(band), ctx.encoder),
    ]
    rows = []
    for source in ctx.model.sources:
        rows.extend(_param_rows(source, ctx.model.units))
    parts.append(
        "<p>The fitted parameters, with their 1σ uncertainties (from the covariance of the weighted fit; "
        "angles in degrees):</p>"
    )
    parts.append(html_table(["source", "parameter", "value", "± 1σ", "relative", "unit"], rows))
    warnings = [f"{s.name}: {s.fit.info['warning']}" for s in ctx.model.sources if s.fit.info.get("warning")]
    parts.extend(html_note(w) for w in warnings)
    return "\n".join(parts)


def previews_section(
    report: RunReport | None, run: RunFile | None, model: LightModel, path: Path, geo: MiddlePosition | None
) -> str:
    pngs = _previews(report, run, model, path)
    if not pngs:
        return html_note("no HDR previews found (the hdr step writes them beside the results as position-NNN.png).")
    box = _ball_box(geo)
    strip = _preview_strip(pngs, box)
    if not strip:
        return html_note("the HDR previews could not be read.")
    caption = (
        f"{min(_PREVIEWS, len(pngs))} of the {len(pngs)} merged HDR frames, spread over the sweep "
        f"(tone-mapped: square root of the radiance{', cropped to the ball' if box else ''}). The light "
        "appears as a blurred spot, its reflection on the ball, that moves across the ball as the light "
        "passes."
    )
    return f"{strip}<p class='caption'>{html.escape(caption)}</p>"

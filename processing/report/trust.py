"""What the report says about trusting the model: the quality banner at the top, and the rig as
the self-calibration fitted it."""

from __future__ import annotations

import html

from processing.lightmodel import LightModel
from processing.report.markup import html_note, html_table


def quality_banner(model: LightModel) -> str:
    """The light model's quality verdict (``quality`` in its JSON) as the page's first words: a
    red banner with the reason when suspect, one line when ok, a note when it was not judged."""
    quality = model.quality
    if not quality:
        return html_note("the light model carries no quality verdict (made without the sweep's χ² judged)")
    figures = (
        f"the templates miss {100 * quality.get('model_error', float('nan')):.1f} % of the sweep's light "
        f"(allowed {100 * quality.get('model_error_allowance', float('nan')):.0f} %; χ²/pixel "
        f"{quality.get('chi2_per_pixel', float('nan')):.3f}), {len(quality.get('unexplained_positions', []))} of "
        f"{quality.get('positions', '?')} positions unexplained"
    )
    refined = quality.get("point_spread_refined")
    if refined:  # the sweep asked for the point spread to be refined: what that did
        figures += f"; the point spread refined from the sweep, {refined}"
    if quality.get("status") == "ok":
        return f'<p class="quality-ok">Quality ok: the templates explain the data ({html.escape(figures)}).</p>'
    return (
        '<div class="quality-suspect"><strong>Quality SUSPECT: do not trust this light model as it is.</strong> '
        f"{html.escape(str(quality.get('reason', '')))}. <br>{html.escape(figures)}. "
        "docs/lab-guide.md says what each alarm means and what to do about it.</div>"
    )


def skipped_note(model: LightModel) -> str:
    """The frames ``--ignore-corrupt`` skipped (the light model's ``skipped_corrupt``), as a red
    banner naming each; empty when none was."""
    skipped = model.provenance.get("skipped_corrupt")
    if not skipped:
        return ""
    frames = "; ".join(
        f"{frame.get('where')} frame {frame.get('frame')} (exposure index {frame.get('frame')}): {frame.get('cause')}"
        for frame in skipped.get("frames", [])
    )
    positions = ", ".join(map(str, skipped.get("positions", []))) or "none"
    return (
        '<div class="quality-suspect"><strong>Corrupt frames skipped (--ignore-corrupt):</strong> '
        f"positions left out: {html.escape(positions)}. {html.escape(frames)}.</div>"
    )


def rig_calibration_part(model: LightModel) -> str:
    """The self-calibration's record (the light model's ``rig_calibration``): each number fitted
    with its 1σ, the held ones and why, χ²/pixel as described and as fitted. Empty without one."""
    record = model.provenance.get("rig_calibration")
    if not isinstance(record, dict):
        return ""
    rows = [
        [name, f"{entry['value']:+.4g} {entry['unit']}", f"{entry['sigma']:.2g} {entry['unit']}", entry["what"]]
        for name, entry in record.get("fitted", {}).items()
    ]
    bounds = record.get("at_bound") or []
    parts = [
        "<p>The rig's numbers fitted to the data (self-calibration): each as a change to the rig description, "
        "with its 1σ (the fit's scatter counted in). The rig as fitted is written beside the light model "
        "(RUN.rig-fitted.toml).</p>",
        html_table(["number", "fitted change", "1σ", "what it is"], rows),
        f"<p>χ²/pixel of the templates over {record.get('pixels')} pixels at positions "
        f"{html.escape(str(record.get('positions')))}: {record.get('chi2_per_pixel_described')} with the rig as "
        f"described, {record.get('chi2_per_pixel')} as fitted; {record.get('searches')} searches for the sources; "
        f"the ball's silhouette from {html.escape(str(record.get('silhouette_frames')))}.</p>",
    ]
    silhouette = record.get("silhouette") or {}
    if silhouette:
        parts.append(
            f"<p>The fitted camera misses the silhouette's {silhouette.get('edge_points')} edge points by "
            f"{silhouette.get('rms_miss_sigma')} σ RMS (σ {silhouette.get('sigma_um')} µm at the ball).</p>"
        )
    if bounds:
        parts.append(html_note(f"ended at the tolerance's bound: {', '.join(bounds)}"))
    held = record.get("held", {})
    if held:
        parts.append(html_table(["held as described", "why"], [[name, why] for name, why in held.items()]))
    return "\n".join(parts)

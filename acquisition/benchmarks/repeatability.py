"""How far apart two runs of the same light come out: the reference simulation (the demo rig,
the five-gaussians truth, noise on, the sources found in the data and the rig self-calibrated)
taken and processed once per seed, each source's place and intensity error scored against
the truth, then the spread over the seeds.

Seeds change the noise (photons, read noise, the arm's read-back, the renderer's samples),
nothing else: what varies between them is what a lab sees between two runs of one light.
The first seed is also taken a second time: a seeded run must come out the same, frame for
frame and number for number (``same_seed_identical``).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.benchmarks.accuracy import bench_accuracy
from drivers.contracts.rig import load_rig, rig_from_dict, rig_to_toml_dict, write_rig


def bench_repeatability(
    *, seeds: int = 10, truth: str = "five-gaussians", rig_path: str | Path | None = None, workdir: Path | None = None
) -> dict[str, Any]:
    """Per seed the accuracy benchmark with the sources found in the data; their spread."""
    data = rig_to_toml_dict(load_rig(rig_path))
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(workdir) if workdir is not None else Path(tmp)
        for seed in [*range(seeds), 0]:
            again = len(rows) == seeds
            data.setdefault("simulation", {})["seed"] = seed
            folder = base / (f"seed-{seed}" + ("-again" if again else ""))
            folder.mkdir(parents=True, exist_ok=True)
            rig_file = write_rig(rig_from_dict(data, f"seed {seed}"), folder / "rig.toml")
            result = bench_accuracy(truth=truth, rig_path=rig_file, layout_from_data=True, workdir=folder)
            rows.append({"seed": seed, "again": again, "result": result, "folder": str(folder)})
    first, repeat = rows[0], rows[-1]
    return {
        "benchmark": "repeatability",
        "truth": truth,
        "seeds": seeds,
        "same_seed_identical": _same_light_model(Path(first["folder"]), Path(repeat["folder"])),
        **spread(rows[:seeds]),
    }


def _same_light_model(a: Path, b: Path) -> bool:
    """Whether two processings wrote the same light model, every number to the last digit
    (the provenance's run id, file names and times aside)."""
    models = [json.loads(next((f / "out").glob("*.light.json")).read_text()) for f in (a, b)]
    return bool(models[0]["sources"] == models[1]["sources"])


def spread(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per truth source over the seeds: the mean offset of its place and its standard deviation
    (µm, u and v), the worst distance, and the worst intensity error (RMS over peak); against
    them what the processing quoted: the centre's 1σ (RMS over the seeds) over the spread, and
    the peak's relative 1σ (the fit's ``a``) over the spread of the peak."""
    names = [s["name"] for s in rows[0]["result"]["sources"]]
    sources = {}
    for name in names:
        entries = [next(s for s in r["result"]["sources"] if s["name"] == name) for r in rows]
        offsets = np.array([e["centre_offset_um"] for e in entries], float)
        sources[name] = {
            "mean_offset_um": [round(float(v), 1) for v in offsets.mean(axis=0)],
            "std_um": [round(float(v), 1) for v in offsets.std(axis=0, ddof=1)] if len(rows) > 1 else None,
            "worst_distance_um": round(float(max(e["centre_error_um"] for e in entries)), 1),
            "worst_rms_rel_error": round(float(max(e["rms_rel_error"] for e in entries)), 5),
            **_quoted_against_spread(entries, offsets),
        }
    ratios = [r for s in sources.values() for r in s.get("quoted_over_spread", []) if r is not None]
    per_seed = [
        {
            "seed": r["seed"],
            "sources_found": r["result"]["sources_found"],
            "worst_distance_um": max(s["centre_error_um"] for s in r["result"]["sources"]),
            "worst_rms_rel_error": r["result"]["max_rms_rel_error"],
            "quality": r["result"]["quality"].get("status"),
            "process_s": r["result"]["process_s"],
        }
        for r in rows
    ]
    return {
        "sources": sources,
        "per_seed": per_seed,
        "worst_distance_um": max(p["worst_distance_um"] for p in per_seed),
        "all_within_100_um": all(p["worst_distance_um"] <= 100.0 for p in per_seed),
        "all_five_found": all(p["sources_found"] == len(names) for p in per_seed),
        "quoted_over_spread_median": round(float(np.median(ratios)), 2) if ratios else None,
        "quoted_within_1_5x": f"{sum(1 / 1.5 <= r <= 1.5 for r in ratios)}/{len(ratios)}" if ratios else None,
    }


def _quoted_against_spread(entries: list[dict[str, Any]], offsets: np.ndarray) -> dict[str, Any]:
    """The quoted 1σ of a source's place (u, v, µm) and peak (relative), RMS over the seeds, and
    each over the spread of what it quotes: [u, v, peak] (empty with fewer than three seeds)."""
    sigmas = [e.get("centre_sigma_um") for e in entries]
    peaks = np.array([e["fit"].get("a", np.nan) for e in entries], float)
    peak_sigma = np.array([e["fit_sigma"].get("a", np.nan) for e in entries], float) / peaks
    out: dict[str, Any] = {"quoted_peak_sigma_rel": round(float(np.sqrt(np.nanmean(peak_sigma**2))), 5)}
    if all(s is not None for s in sigmas):
        quoted_um = np.array(sigmas, dtype=float)
        out["quoted_sigma_um"] = [round(float(v), 1) for v in np.sqrt(np.mean(quoted_um**2, axis=0))]
    if len(entries) >= 3:
        spread = [*offsets.std(axis=0, ddof=1), float(np.nanstd(peaks, ddof=1) / np.nanmean(peaks))]
        out["peak_spread_rel"] = round(spread[2], 5)
        quoted = [*out.get("quoted_sigma_um", [np.nan, np.nan]), out["quoted_peak_sigma_rel"]]
        out["quoted_over_spread"] = [
            round(q / s, 2) if s > 0 and np.isfinite(q) else None for q, s in zip(quoted, spread, strict=True)
        ]
    return out

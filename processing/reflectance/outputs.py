"""The reflectance's files: albedo maps (OpenEXR, PNG), the reason map, textures, the per-point HDF5, the summary."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import h5py
import numpy as np
import OpenEXR

from drivers.pose import Pose
from processing.exports.pbrt import write_pbrt_lights
from processing.lightmodel import LightModel, json_ready
from processing.reflectance.codes import PIXEL_CODES, PIXEL_COLOURS, PIXEL_SHORT, SAMPLE_CODES, SAMPLE_SHORT
from processing.reflectance.estimate import ReflectanceResult
from processing.reflectance.lights import LIGHT_MODELS
from processing.reflectance.maps import reflectance_profiles, uv_texture
from processing.reflectance.material_outputs import write_material_outputs
from processing.reflectance.material_outputs import write_png as write_rgb_png
from processing.reflectance.page import reflectance_profiles_figure, write_reflectance_report

log = logging.getLogger("mirrorgonio.processing")


def _write_exr(path: Path, rgb: np.ndarray) -> Path:
    """An RGB float32 OpenEXR that keeps NaN (``processing.images.write_exr`` writes 0 there)."""

    data = np.ascontiguousarray(rgb, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": data}) as exr:
        exr.write(str(path))
    return path


def _write_rgba_png(path: Path, rgba: np.ndarray) -> Path:

    if not cv2.imwrite(str(path), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA)):
        raise OSError(f"{path}: could not write the PNG")
    return path


def _albedo_png(path: Path, rgb: np.ndarray, scale: float) -> Path:
    """ρ/scale, display gamma 1/2.2, transparent where there is no albedo."""
    finite = np.all(np.isfinite(rgb), axis=-1)
    shown = np.clip(np.where(finite[..., None], rgb, 0.0) / scale, 0.0, 1.0) ** (1.0 / 2.2)
    rgba = np.zeros((*rgb.shape[:2], 4), np.uint8)
    rgba[..., :3] = (255.0 * shown + 0.5).astype(np.uint8)
    rgba[..., 3] = np.where(finite, 255, 0)
    return _write_rgba_png(path, rgba)


def _reason_png(path: Path, reason: np.ndarray) -> Path:
    rgba = np.full((*reason.shape, 4), 255, np.uint8)
    for code, colour in PIXEL_COLOURS.items():
        rgba[reason == code, :3] = colour
    return _write_rgba_png(path, rgba)


def _write_points(path: Path, result: ReflectanceResult, run_id: str | None) -> Path:
    """``reflectance.h5``: the per-point data, the code tables and the object run's id."""
    with h5py.File(path, "w") as f:
        f.attrs.update(
            format="mirrorgonio-reflectance",
            format_version=1,
            pixel_codes=json.dumps(PIXEL_CODES),
            sample_codes=json.dumps(SAMPLE_CODES),
            methods=json.dumps(list(result.methods)),
        )
        if run_id:  # whose reflectance this is (the overwrite guard reads it)
            f.attrs["run_id"] = str(run_id)
        f["reason"] = result.reason
        f["rows"], f["cols"] = result.rows, result.cols
        f["points"], f["normals"], f["faces"] = result.points, result.normals, result.faces
        f["heights"] = result.heights
        f["valid"] = result.valid
        f["sample_code"] = result.sample_code
        f["radiance"] = result.radiance
        if result.uv is not None:
            f["uv"] = result.uv
        for m in result.methods:
            f[f"rho/{m}"] = result.rho_points[m]
            f[f"irradiance/{m}"] = result.irradiance[m]
            f[f"irradiance_rgb/{m}"] = result.irradiance_rgb(m)
    return path


#: The files a reflectance writes into its folder whatever the mesh, and those per light model.
FIXED_OUTPUTS = ("reflectance.json", "reflectance.h5", "report.html", "reasons.png", "profiles.png")
PER_MODEL_OUTPUTS = (
    "albedo-{}.exr",
    "albedo-{}.png",
    "texture-{}.exr",
    "texture-{}.png",
    "brdf-{}.exr",
    "basecolor-{}.png",
    "confidence-{}.png",
    "object-{}.glb",
)


@dataclass
class PlacedLight:
    """The light model where the run put it: per position its pose in the mesh's own frame."""

    model: LightModel
    poses: dict[str, Pose]
    calibration: float | None = None

    @classmethod
    def from_run(
        cls, model: LightModel, poses: Sequence[Pose], positions: Iterable[int], object_pose: Pose | None
    ) -> PlacedLight:
        """The rig-frame light poses of a run's ``positions`` in the frame of an object at ``object_pose``."""
        rig_to_object = (object_pose or Pose(0.0, 0.0, 0.0)).inverse()
        placed = {f"position-{k:02d}": rig_to_object.compose(p) for k, p in zip(list(positions), poses, strict=True)}
        return cls(model, placed)

    def write(self, folder: Path) -> dict[str, Path]:
        """``light.pbrt`` (the light frame), ``light-<position>.pbrt`` and the tables, by file name."""
        written = write_pbrt_lights(
            self.model,
            folder / "light.pbrt",
            poses=list(self.poses.values()),
            pose_names=list(self.poses),
            calibration=self.calibration,
        )
        return {f"lights/{path.name}": path for path in written}


def outputs_in(out_dir: str | os.PathLike[str]) -> list[Path]:
    """Every file :func:`write_outputs` may write into ``out_dir`` (the textures only for a mesh
    with UVs): what must not hold another run's reflectance before it is written."""
    out = Path(out_dir)
    per_model = [out / name.format(m) for m in LIGHT_MODELS for name in PER_MODEL_OUTPUTS]
    return [out / name for name in FIXED_OUTPUTS] + per_model


def write_outputs(
    result: ReflectanceResult,
    out_dir: str | os.PathLike[str],
    *,
    texture_size: int = 1024,
    bins: int = 24,
    metadata: dict[str, Any] | None = None,
    mesh_object_frame: Any | None = None,
    relit: dict[str, np.ndarray] | None = None,
    placed_light: PlacedLight | None = None,
) -> dict[str, Path]:
    """Write the files of ``docs/reflectance.md`` into ``out_dir``; returns them by name.

    Per method ``albedo-<method>.exr`` (NaN where invalid) and ``.png``; ``reasons.png``;
    ``texture-<method>.exr`` and ``.png`` when the mesh has UVs; ``profiles.png``;
    ``reflectance.h5`` (the per-point data); ``reflectance.json`` (the summary); and
    ``report.html``. With the BRDF fitted (``result.materials``), per method the
    ``brdf-<method>.exr`` layers, ``basecolor-`` and ``confidence-<method>.png`` and, for a
    mesh with UVs given in its own frame, ``object-<method>.glb``
    (:mod:`~processing.reflectance.material_outputs`); ``relit`` images (8-bit RGB by name,
    :func:`~processing.reflectance.materials.relighting_images`) as ``<name>.png``; with a
    ``placed_light``, the light as pbrt-v4 goniometric lights at every position of the run, in
    the mesh's own frame (``lights/``, :mod:`~processing.exports.pbrt`).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    finite = [v[np.isfinite(v)] for v in result.rho_points.values()]
    values = np.concatenate(finite) if finite else np.zeros(0)
    scale = float(np.percentile(values, 99.5)) if values.size else 1.0
    scale = scale if scale > 0 else 1.0
    for m in result.methods:
        files[f"albedo-{m}.exr"] = _write_exr(out / f"albedo-{m}.exr", result.rho[m])
        files[f"albedo-{m}.png"] = _albedo_png(out / f"albedo-{m}.png", result.rho[m], scale)
    files["reasons.png"] = _reason_png(out / "reasons.png", result.reason)
    textures = {}
    if result.uv is not None:
        for m in result.methods:
            texture = uv_texture(result, m, texture_size)
            assert texture is not None  # the mesh has UVs
            files[f"texture-{m}.exr"] = _write_exr(out / f"texture-{m}.exr", texture)
            files[f"texture-{m}.png"] = textures[m] = _albedo_png(out / f"texture-{m}.png", texture, scale)
    profiles = reflectance_profiles(result, bins)
    fig = reflectance_profiles_figure(profiles, result.methods)
    fig.savefig(out / "profiles.png", dpi=100)
    files["profiles.png"] = out / "profiles.png"

    files["reflectance.h5"] = _write_points(out / "reflectance.h5", result, (metadata or {}).get("run_id"))
    if result.materials is not None:
        files.update(write_material_outputs(result.materials, result, out, mesh_object_frame, texture_size))
    for name, image in (relit or {}).items():
        files[f"{name}.png"] = write_rgb_png(out / f"{name}.png", image)
    if placed_light is not None:
        files.update(placed_light.write(out / "lights"))

    summary = {
        **(metadata or {}),
        **result.summary(),
        "png_scale": scale,
        "brdf": result.materials.summary() if result.materials is not None else None,
        "profiles": profiles,
        "pixel_codes": {str(c): PIXEL_SHORT[c] for c in PIXEL_CODES},
        "sample_codes": {str(c): SAMPLE_SHORT[c] for c in SAMPLE_CODES},
    }
    files["report.html"] = out / "report.html"
    files["reflectance.json"] = out / "reflectance.json"
    summary["outputs"] = {name: str(path) for name, path in files.items()}

    (out / "reflectance.json").write_text(json.dumps(json_ready(summary), indent=2) + "\n", encoding="utf-8")
    write_reflectance_report(
        out / "report.html",
        summary,
        images={
            **{f"albedo-{m}": out / f"albedo-{m}.png" for m in result.methods},
            "reasons": out / "reasons.png",
            "profiles": out / "profiles.png",
            **{f"texture-{m}": p for m, p in textures.items()},
            **{
                name.removesuffix(".png"): path
                for name, path in files.items()
                if name.startswith(("relit-", "basecolor-", "confidence-"))
            },
        },
    )
    result.outputs = files
    return files

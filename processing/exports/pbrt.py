"""Each source of a light model as a pbrt-v4 goniometric light: the near field for renderers.

A far-field file (IES, LDT) puts the whole light at one point; at the distances an object is
lit from, the sources' places matter. pbrt-v4's ``goniometric`` light is a point with its
own radiant intensity table, so a light model becomes one goniometric light per source, at
the source's place, each with its own table:

- ``source-<name>.exr``: a square single-channel (``Y``) float image, the source's
  ``I_s(θ, φ)`` in pbrt's equal-area octahedral parameterisation (Clarberg, "Fast
  equal-area mapping of the (hemi)sphere using SIMD", JGT 2008), which pbrt looks up with
  the nearest pixel. Every pixel covers the same solid angle, ``4π / n²``, so the source's
  flux is the image's mean × 4π.
- ``<name>.pbrt``: the lights, to ``Include`` after ``WorldBegin``: per source an
  ``AttributeBegin`` block with its ``Transform`` and ``LightSource "goniometric"`` (the
  image, ``rgb I`` its colour, ``scale`` its units).

Frames. pbrt swaps the light space's y and z before the lookup (its tables are y-up). The
transform written is ``world ← light frame ← source's place ← R``, where ``R`` turns the
table's frame a quarter turn about x, so that after pbrt's swap the image's centre is the
source's axis (the light frame's +z) and a direction ``d`` of the light frame is looked up
at ``(d_x, −d_y, d_z)``: the forward hemisphere is the image's inner diamond, the back
(zero: the sources are on a plane) its corners.

Units. pbrt divides ``scale`` by the photometric value of ``I``'s illuminant, so that a
table value is in candela: a calibrated model (``calibration`` candela per model unit)
gives candela, an uncalibrated one relative intensities (the file says which). The colour
is the source's camera-channel ratio (mean 1), which is close to, but not, linear sRGB.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import OpenEXR

from drivers.pose import Pose
from processing.exports.far_field import ExportError, checked_extrapolation, write_text
from processing.lightmodel import LightModel, SourceModel
from processing.options import Extrapolation

#: Pixels per side of a source's table: 512² pixels of 4π/512² sr, about 0.4° across.
TABLE_PIXELS = 512
#: The table's frame in the source's frame: a quarter turn about x (the table's +y is the axis +z).
QUARTER_TURN_X = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def equal_area_square_to_sphere(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit directions (…, 3) of points ``(u, v)`` of the unit square, Clarberg's equal-area map.

    The square's centre is +z, its corners −z; the map is the one pbrt-v4 uses for its
    goniometric lights and environment maps.

    Examples
    --------
    >>> equal_area_square_to_sphere(np.array([0.5, 1.0]), np.array([0.5, 0.5])).round(12).tolist()
    [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
    """
    a, b = 2.0 * np.asarray(u, float) - 1.0, 2.0 * np.asarray(v, float) - 1.0
    au, av = np.abs(a), np.abs(b)
    signed = 1.0 - (au + av)  # the signed distance from the diagonal: > 0 in the northern diamond
    r = 1.0 - np.abs(signed)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = np.where(r == 0, 1.0, (av - au) / r + 1.0) * (math.pi / 4)
    z = np.copysign(1.0 - r**2, signed)
    ring = r * np.sqrt(np.maximum(2.0 - r**2, 0.0))
    return np.stack([np.copysign(np.cos(phi), a) * ring, np.copysign(np.sin(phi), b) * ring, z], axis=-1)


def table_directions(pixels: int) -> np.ndarray:
    """The light-frame direction (pixels, pixels, 3) each table pixel's centre stands for.

    Row ``y`` and column ``x`` are the image's (row 0 first in the file), at
    ``(u, v) = ((x + ½)/n, (y + ½)/n)``; pbrt's swap and :data:`QUARTER_TURN_X` take its
    equal-area direction ``w`` to ``d = (w_x, −w_y, w_z)``.
    """
    centres = (np.arange(pixels) + 0.5) / pixels
    w = equal_area_square_to_sphere(centres[None, :], centres[:, None])
    return w * np.array([1.0, -1.0, 1.0])


def source_table(source: SourceModel, pixels: int = TABLE_PIXELS, extrapolation: str = "fitted") -> np.ndarray:
    """``I_s`` at every table pixel (pixels, pixels) float32; zero behind the light's plane and,
    with ``extrapolation="none"``, beyond the θ the sweep measured."""
    d = table_directions(pixels)
    theta = np.arccos(np.clip(d[..., 2], -1.0, 1.0))
    phi = np.arctan2(d[..., 1], d[..., 0])
    table = source.intensity(theta, phi)
    if extrapolation == Extrapolation.NONE.value:
        table = np.where(theta <= source.fit.theta_range[1], table, 0.0)
    return table.astype(np.float32)


def _column_major(matrix: np.ndarray) -> str:
    """A 4×4 matrix as pbrt's ``Transform`` lists it: column by column (the translation last)."""
    return " ".join(f"{x:.9g}" for x in matrix.T.reshape(-1))


def source_transform(source: SourceModel, world_from_light: Pose) -> np.ndarray:
    """The 4×4 ``world ← table frame`` of one source: its place on the light plane and :data:`QUARTER_TURN_X`."""
    local = np.eye(4)
    local[:3, :3] = QUARTER_TURN_X
    local[:3, 3] = (source.centre_m[0], source.centre_m[1], 0.0)
    return world_from_light.matrix() @ local


def write_pbrt_lights(
    model: LightModel,
    path: str | Path,
    *,
    poses: Sequence[Pose] | None = None,
    pose_names: Sequence[str] | None = None,
    calibration: float | None = None,
    extrapolation: str = "fitted",
    pixels: int = TABLE_PIXELS,
) -> list[Path]:
    """Write ``model``'s sources as pbrt-v4 goniometric lights (see the module's docstring).

    Parameters
    ----------
    model : LightModel
        The light.
    path : path
        The ``.pbrt`` file of the light in its own frame; the tables go beside it.
    poses, pose_names : sequence of Pose, sequence of str, optional
        Also one ``<stem>-<pose name>.pbrt`` per pose (``world ← light frame``), sharing the
        tables: the light where a run put it, in the frame of the scene it lit.
    calibration : float, optional
        Candela per model unit; the tables are then in candela.
    extrapolation : str
        ``"fitted"`` or ``"none"`` (zero beyond the measured θ), as the far-field files.
    pixels : int
        The tables' side.

    Returns
    -------
    list of Path
        The ``.pbrt`` files, then the tables.
    """
    path = Path(path)
    extrapolation = checked_extrapolation(path, extrapolation)
    if calibration is not None and not (math.isfinite(calibration) and calibration > 0):
        raise ExportError(f"{path}: calibration: must be a number > 0 (candela per model unit), got {calibration}")
    if pixels < 16:
        raise ExportError(f"{path}: pixels: a table needs at least 16 pixels a side, got {pixels}")
    poses = list(poses or [])
    names = list(pose_names) if pose_names is not None else [f"{k:02d}" for k in range(len(poses))]
    if len(names) != len(poses):
        raise ExportError(f"{path}: pose_names: {len(names)} names for {len(poses)} poses")
    path.parent.mkdir(parents=True, exist_ok=True)
    tables = []
    for source in model.sources:
        table = path.with_name(f"{path.stem}-source-{_file_safe(source.name)}.exr")
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {"Y": source_table(source, pixels, extrapolation)}) as exr:
            exr.write(str(table))
        tables.append(table)
    scenes = [_write_scene(path, model, tables, Pose(0.0, 0.0, 0.0), "the light frame", calibration, extrapolation)]
    for name, pose in zip(names, poses, strict=True):
        where = f"light pose {name} (world = the frame the poses are given in)"
        placed = path.with_name(f"{path.stem}-{name}.pbrt")
        scenes.append(_write_scene(placed, model, tables, pose, where, calibration, extrapolation))
    return scenes + tables


def _file_safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def _write_scene(
    path: Path,
    model: LightModel,
    tables: list[Path],
    pose: Pose,
    where: str,
    calibration: float | None,
    extrapolation: str,
) -> Path:
    units = f"candela ({calibration:.6g} cd per model unit)" if calibration else f"relative ({model.units})"
    lines = [
        f"# mirrorgonio light model: {len(model.sources)} sources as pbrt-v4 goniometric lights",
        f"# placed at {where}; metres",
        f"# intensities: {units}; beyond the measured angles: {extrapolation}",
        "# Include this file after WorldBegin.",
    ]
    for source, table in zip(model.sources, tables, strict=True):
        lo, hi = (math.degrees(t) for t in source.fit.theta_range)
        r, g, b = source.colour
        lines += [
            "AttributeBegin",
            f'  # source "{source.name}": centre ({source.centre_m[0]:.6g}, {source.centre_m[1]:.6g}) m on the'
            f" light plane, measured {lo:.1f}-{hi:.1f} degrees, flux {source.flux():.6g} (model units x sr)",
            f"  Transform [ {_column_major(source_transform(source, pose))} ]",
            f'  LightSource "goniometric" "string filename" "{table.name}"',
            f'    "rgb I" [ {r:.6g} {g:.6g} {b:.6g} ] "float scale" {calibration or 1.0:.9g}',
            "AttributeEnd",
        ]
    return write_text(path, lines, "\n")

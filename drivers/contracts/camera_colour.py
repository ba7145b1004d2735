"""A camera's colour description as its raw files carry it: the DNG colour matrices.

The run file keeps the description of the camera its frames came from (``docs/run-file.md``,
"Camera colour"), read from the first raw file of the run: a plain dict of

- ``color_matrix_1`` (and optionally ``color_matrix_2``): 3×3, row-major, XYZ → camera
  native RGB under ``calibration_illuminant_1`` (``_2``), as the DNG tags ColorMatrix1/2;
- ``calibration_illuminant_1`` (``_2``): the EXIF LightSource code of that illuminant (17
  CIE A, 21 D65, ...; :data:`ILLUMINANT_CCT_K`);
- ``as_shot_neutral`` (optional): the camera RGB of a neutral under the shot's light;
- ``forward_matrix_1``/``_2`` (optional): white-balanced camera → XYZ (D50), kept as read;
- ``source``: where the matrices were read ("DNG tags", "LibRaw").
"""

from __future__ import annotations

import math
from typing import Any

#: The correlated colour temperature of each EXIF LightSource code a DNG names as its
#: calibration illuminant (as the DNG SDK's ``IlluminantToTemperature`` takes them), kelvin.
ILLUMINANT_CCT_K: dict[int, float] = {
    1: 5500.0,  # daylight
    2: 3450.0,  # fluorescent
    3: 2856.0,  # tungsten
    4: 5500.0,  # flash
    9: 5500.0,  # fine weather
    10: 6500.0,  # cloudy
    11: 7500.0,  # shade
    12: 6430.0,  # daylight fluorescent
    13: 5000.0,  # day white fluorescent
    14: 4150.0,  # cool white fluorescent
    15: 3450.0,  # white fluorescent
    16: 2940.0,  # warm white fluorescent
    17: 2856.0,  # standard light A
    18: 4874.0,  # standard light B
    19: 6774.0,  # standard light C
    20: 5503.0,  # D55
    21: 6504.0,  # D65
    22: 7504.0,  # D75
    23: 5003.0,  # D50
    24: 3200.0,  # ISO studio tungsten
}


class CameraColourError(ValueError):
    """A colour description that is not one (one line naming the field)."""


def _matrix(value: Any, name: str) -> list[list[float]]:
    try:
        rows = [[float(v) for v in row] for row in value]
    except (TypeError, ValueError):
        raise CameraColourError(f"{name}: must be a 3x3 matrix of numbers") from None
    if len(rows) != 3 or any(len(row) != 3 for row in rows) or not all(math.isfinite(v) for r in rows for v in r):
        raise CameraColourError(f"{name}: must be a 3x3 matrix of finite numbers")
    det = (
        rows[0][0] * (rows[1][1] * rows[2][2] - rows[1][2] * rows[2][1])
        - rows[0][1] * (rows[1][0] * rows[2][2] - rows[1][2] * rows[2][0])
        + rows[0][2] * (rows[1][0] * rows[2][1] - rows[1][1] * rows[2][0])
    )
    if abs(det) < 1e-12:
        raise CameraColourError(f"{name}: singular (no inverse maps camera RGB to XYZ)")
    return rows


def checked_camera_colour(description: Any, where: str = "camera colour") -> dict[str, Any]:
    """The description checked and in plain numbers; an empty dict stays empty (no matrices known).

    Raises
    ------
    CameraColourError
        One line naming ``where`` and the field: not a dict, no ``color_matrix_1``, a matrix
        that is not 3×3, finite and invertible, an illuminant code not in
        :data:`ILLUMINANT_CCT_K`, or a neutral that is not three positive numbers.
    """
    if not isinstance(description, dict):
        raise CameraColourError(f"{where}: must be an object, not {type(description).__name__}")
    if not description:
        return {}
    out: dict[str, Any] = {"source": str(description.get("source", ""))}
    if "color_matrix_1" not in description:
        raise CameraColourError(f"{where}: color_matrix_1: missing")
    for k in (1, 2):
        matrix = description.get(f"color_matrix_{k}")
        if matrix is None:
            continue
        out[f"color_matrix_{k}"] = _matrix(matrix, f"{where}: color_matrix_{k}")
        code = description.get(f"calibration_illuminant_{k}", 21 if k == 1 else None)
        if isinstance(code, bool) or code not in ILLUMINANT_CCT_K:
            raise CameraColourError(
                f"{where}: calibration_illuminant_{k}: {code!r} is not a DNG calibration illuminant "
                f"({', '.join(str(c) for c in ILLUMINANT_CCT_K)})"
            )
        out[f"calibration_illuminant_{k}"] = int(code)
    for k in (1, 2):
        if description.get(f"forward_matrix_{k}") is not None:
            out[f"forward_matrix_{k}"] = _matrix(description[f"forward_matrix_{k}"], f"{where}: forward_matrix_{k}")
    neutral = description.get("as_shot_neutral")
    if neutral is not None:
        try:
            values = [float(v) for v in neutral]
        except (TypeError, ValueError):
            values = []
        if len(values) != 3 or not all(math.isfinite(v) and v > 0 for v in values):
            raise CameraColourError(f"{where}: as_shot_neutral: must be three positive numbers")
        out["as_shot_neutral"] = values
    return out

"""What the far-field files (IES, EULUMDAT) share: the far field's table and its scaling, the numbers and the text."""

from __future__ import annotations

import math
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from processing.lightmodel import LightModel
from processing.options import Extrapolation
from processing.photometry import Photometry, far_field


class ExportError(ValueError):
    """An export that cannot be written (one line naming the file and the field)."""


def plain_number(x: float, digits: int = 6) -> str:
    """A number in plain positional notation (no exponent), ``digits`` significant digits."""
    x = float(x)
    if x == 0 or not math.isfinite(x):
        return "0"
    return np.format_float_positional(x, precision=digits, unique=False, fractional=False, trim="-")


def angle_grid(path: Path, name: str, step: float, stop: float) -> np.ndarray:
    if not (step > 0 and math.isfinite(step)):
        raise ExportError(f"{path}: {name}: must be a positive number of degrees, got {step!r}")
    n = stop / step
    if abs(n - round(n)) > 1e-9:
        raise ExportError(f"{path}: {name}: {step:g}° does not divide {stop:g}°")
    return np.linspace(0.0, stop, int(round(n)) + 1)


def far_field_table(
    model: LightModel, gamma_deg: np.ndarray, c_deg: np.ndarray, extrapolation: str = Extrapolation.FITTED
) -> np.ndarray:
    """``Σ_s I_s`` on a (C, γ) grid, shape ``(len(c), len(gamma))``, in model units; beyond each
    source's measured θ the fits' extrapolation, or zero (``extrapolation="none"``)."""
    theta = np.radians(np.asarray(gamma_deg, dtype=float))[None, :]
    phi = np.radians(np.mod(-np.asarray(c_deg, dtype=float), 360.0))[:, None]
    return far_field(model, theta, phi, extrapolation)


def checked_extrapolation(path: Path, extrapolation: str) -> str:
    """``"fitted"`` or ``"none"`` (:class:`~processing.options.Extrapolation`), or one line naming the file."""
    try:
        return Extrapolation(extrapolation).value
    except ValueError:
        choices = ", ".join(e.value for e in Extrapolation)
        raise ExportError(f"{path}: extrapolation: {extrapolation!r} is not one of {choices}") from None


def measured_range_text(summary: Photometry) -> str:
    """What the table holds beyond the measured θ, in a sentence (the files' free text)."""
    every, some = summary.light_theta_max_deg
    reach = f"{every:.1f} degrees" if some - every < 0.05 else f"{every:.1f} degrees (every source; {some:.1f} some)"
    if summary.extrapolation == Extrapolation.NONE:
        return (
            f"Measured range only: the sweep measured vertical angles up to {reach}; beyond, the table is zero "
            f"(the fits would put {100 * summary.fitted_beyond_fraction:.1f} % of the flux there)."
        )
    return (
        f"The sweep measured vertical angles up to {reach}; beyond, the table holds the fits' extrapolation, "
        f"{100 * summary.beyond_fraction:.1f} % of its flux."
    )


def far_field_scaling(
    path: Path, flux: float, table: np.ndarray, calibration: float | None, lamp_lumens: float | None
) -> tuple[float, float, bool]:
    """``(factor, lamp_flux, absolute)``: what multiplies the model's intensities, and the lamp
    flux; ``flux`` is the table's light's, in model units × sr."""
    if calibration is not None and lamp_lumens is not None:
        raise ExportError(
            f"{path}: give calibration (absolute candela) or lamp_lumens (relative, lumen scaled), not both"
        )
    if not (flux > 0) or not np.any(table > 0):
        raise ExportError(f"{path}: the light model emits no flux in front of its plane")
    if calibration is not None:
        calibration = float(calibration)
        if not (calibration > 0 and math.isfinite(calibration)):
            raise ExportError(
                f"{path}: calibration: must be a positive factor (cd per model unit), got {calibration!r}"
            )
        return calibration, calibration * flux, True
    if lamp_lumens is not None:
        lamp_lumens = float(lamp_lumens)
        if not (lamp_lumens > 0 and math.isfinite(lamp_lumens)):
            raise ExportError(f"{path}: lamp_lumens: must be a positive number of lumens, got {lamp_lumens!r}")
        return lamp_lumens / flux, lamp_lumens, False
    factor = 1000.0 / float(np.max(table))
    return factor, factor * flux, False


def luminous_opening(model: LightModel) -> tuple[float, float]:
    """``(length along light x, width along light y)`` of the sources' discs, metres."""
    u = np.array([s.centre_m[0] for s in model.sources])
    v = np.array([s.centre_m[1] for s in model.sources])
    r = np.array([s.radius_m for s in model.sources])
    return float(np.max(u + r) - np.min(u - r)), float(np.max(v + r) - np.min(v - r))


def theta_cover(model: LightModel) -> tuple[float, float]:
    lo = min(s.fit.theta_range[0] for s in model.sources)
    hi = max(s.fit.theta_range[1] for s in model.sources)
    return math.degrees(lo), math.degrees(hi)


def write_text(path: Path, lines: list[str], newline: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="ascii", errors="replace", newline="") as f:
        f.write(newline.join(lines) + newline)
    os.replace(tmp, path)
    return path


def wrap_numbers(values: Iterable[str], per_line: int = 10) -> list[str]:
    values = list(values)
    return [" ".join(values[i : i + per_line]) for i in range(0, len(values), per_line)] or [""]


def ascii_only(text: str) -> str:
    return "".join(c if 32 <= ord(c) < 127 else "?" for c in str(text))


def keyword_lines(name: str, text: str, width: int = 132) -> list[str]:
    """``[NAME] text``, continued on ``[MORE]`` lines so that no line passes ``width`` characters."""
    text = " ".join(ascii_only(text).split())
    head, lines = f"[{name}] ", []
    while True:
        room = width - len(head)
        if len(text) <= room:
            lines.append((head + text).rstrip())
            return lines
        cut = text.rfind(" ", 0, room)
        cut = room if cut <= 0 else cut
        lines.append(head + text[:cut].rstrip())
        text, head = text[cut:].lstrip(), "[MORE] "


def describe_light(model: LightModel) -> tuple[str, str, str]:
    prov = model.provenance
    run = str(prov.get("run_id") or "unknown run")
    rig = str(prov.get("rig") or "unknown rig")
    methods = sorted({s.fit.method for s in model.sources})
    return run, rig, ", ".join(methods)


def absolute_note(model: LightModel) -> str | None:
    """The light files' words on an absolute scale's uncertainty and origin (ASCII), from the
    model's ``photometry.absolute``; None without one."""
    absolute = model.photometry.get("absolute")
    if absolute is None:
        return None
    calibration = absolute["calibration"]
    plain = str.maketrans({"θ": "theta ", "φ": "phi ", "°": " deg", "±": "+-", "σ": "sigma"})
    text = (
        f"Candela through the camera's photometric calibration ({calibration['reference']}; "
        f"1-sigma {100 * absolute['relative_uncertainty']:.2f} % of the scale, colour included); "
        f"total flux {absolute['flux_lm']:.5g} lm +- {absolute['flux_lm_sigma']:.2g} (1 sigma)."
    )
    return ascii_only(text.translate(plain))


def intensity_uncertainty(model: LightModel, theta_max_deg: float) -> tuple[float, float]:
    """The whole light's 1σ over its measured θ, as fractions of its intensity: the median and
    the largest where the light holds at least a tenth of its peak. Each source's band
    (:meth:`processing.fit.IntensityFit.band`), the sources taken as independent, on the
    C-planes every 15°."""
    theta = np.radians(np.linspace(0.0, theta_max_deg, 46))[None, :]
    phi = np.radians(np.arange(0.0, 360.0, 15.0))[:, None]
    total = np.zeros((phi.size, theta.size))
    variance = np.zeros_like(total)
    for source in model.sources:
        total += source.intensity(theta, phi)
        variance += source.fit.band(theta, phi) ** 2
    strong = total >= 0.1 * float(total.max())
    relative = np.sqrt(variance[strong]) / total[strong]
    return float(np.median(relative)), float(relative.max())

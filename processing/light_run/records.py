"""What a light run did: its report, and the camera's numbers it fitted to the data."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from drivers.contracts.rig import Rig
from drivers.contracts.runfile import CorruptFrame
from processing.hdr.model import NoiseModel
from processing.light_run.position import PositionResult
from processing.lightmodel import describe_fitted
from processing.rig_fit import FITTED, RigCorrection, RigFit


@dataclass(frozen=True)
class FittedNumber:
    """One of the camera's numbers fitted to the data: its aperture's diameter or its sensor
    distance, in metres.

    Attributes
    ----------
    fitted_m : float or None
        The number that explains the data best; None where no fit succeeded.
    described_m : float or None
        The rig description's.
    chi2_per_pixel, chi2_per_pixel_described : float or None
        The templates' χ² per pixel at the fitted and at the described number.
    pixels : int
        The pixels χ² is summed over.
    positions : tuple of int
        The merged positions the fit used.
    evaluations : int
        χ² computed.
    searches : int
        With the sources searched for in the data: the search this fit followed (0 with a
        given layout).
    sources_refitted : bool or None
        For the sensor distance: the sources' places refitted at each trial distance.
    failed : str
        Why the last fit failed (the number from before it is kept); empty otherwise.
    """

    fitted_m: float | None = None
    described_m: float | None = None
    chi2_per_pixel: float | None = None
    chi2_per_pixel_described: float | None = None
    pixels: int = 0
    positions: tuple[int, ...] = ()
    evaluations: int = 0
    searches: int = 0
    sources_refitted: bool | None = None
    failed: str = ""

    def record(self) -> dict:
        """The fields that say something, as plain JSON values (the light model's provenance,
        the benchmarks' JSON)."""
        return {
            key: list(value) if isinstance(value, tuple) else value
            for key, value in asdict(self).items()
            if value not in (None, "", ()) and not (key == "searches" and value == 0)
        }

    def describe(self, digits: str) -> str:
        """In words, as the command line says it: "0.2004 mm fitted to the data (the rig says 0.2 mm; ...)"."""
        return describe_fitted(self.record(), digits)


def camera_provenance(fit: FittedNumber | None, option: str) -> dict | str:
    """The light model's ``aperture_m`` or ``sensor_distance_m``: the fit's record, or how the
    rig's number came to be used."""
    if fit is not None and fit.fitted_m is not None:
        return fit.record() | {"how": f"fitted to the data ({option})"}
    if fit is not None and fit.failed:
        return f"as described by the rig (the fit to the data failed: {fit.failed})"
    return "as described by the rig"


@dataclass(frozen=True)
class RigCalibration:
    """What the self-calibration did.

    Attributes
    ----------
    fit : RigFit
        The last fit: the correction with its 1σ, χ² as described and as fitted.
    start : RigCorrection
        Where the fits started: the silhouette's coarse correction, or none.
    silhouette : str
        The calibration frames the silhouette was measured on, or why it was not.
    searches : int
        Searches for the sources made.
    positions : tuple of int
        The merged positions the fits used.
    rig : Rig
        The rig as fitted (what ``RUN.rig-fitted.toml`` holds).
    """

    fit: RigFit
    start: RigCorrection
    silhouette: str
    searches: int
    positions: tuple[int, ...]
    rig: Rig

    @property
    def correction(self) -> RigCorrection:
        return self.fit.correction

    def summary(self) -> list[str]:
        """In words, one line per number: "camera_yaw -0.012 ± 0.0008 deg" and χ²/pixel."""
        lines = [
            f"{n.name} {v:+.4g} ± {s:.2g} {n.unit}"
            for n, v, s in zip(FITTED, self.fit.correction.values, self.fit.sigma, strict=True)
            if n.name not in self.fit.held
        ]
        lines.append(
            f"χ²/pixel {self.fit.chi2_described / self.fit.pixels:.4f} as described, "
            f"{self.fit.chi2 / self.fit.pixels:.4f} as fitted ({self.fit.pixels} pixels)"
        )
        return lines

    def camera_record(self, number: str) -> dict:
        """The light model's ``aperture_m`` (``number`` "pinhole") or ``sensor_distance_m``
        ("sensor_distance") as the self-calibration fitted it, in metres: the fitted value, its
        1σ, the one described, and the joint fit's χ²/pixel as fitted and as described."""
        field = {"pinhole": "pinhole_diameter_m", "sensor_distance": "sensor_distance_m"}[number]
        percent = self.correction.value(number)
        sigma = self.fit.sigma[[n.name for n in FITTED].index(number)]
        fitted = float(getattr(self.rig.camera, field))
        described = fitted / (1.0 + percent / 100.0)
        return {
            "fitted_m": fitted,
            "sigma_m": described * sigma / 100.0,
            "described_m": described,
            "chi2_per_pixel": round(self.fit.chi2 / self.fit.pixels, 5),
            "chi2_per_pixel_described": round(self.fit.chi2_described / self.fit.pixels, 5),
            "how": "fitted to the data with the rest of the rig (self-calibration)",
        }

    def record(self) -> dict:
        """The light model's ``rig_calibration``: each number fitted (value, 1σ, unit), each
        held with why, χ²/pixel as described and as fitted, where it started."""
        return self.fit.record() | {
            "silhouette_frames": self.silhouette,
            "start": {n.name: round(v, 6) for n, v in zip(FITTED, self.start.values, strict=True) if v},
            "searches": self.searches,
            "positions": list(self.positions),
        }


@dataclass(frozen=True)
class Quality:
    """The verdict on a light model (:func:`processing.light_run.quality.judge`): ``ok`` or
    ``suspect``, with the reasons and the figures: χ² per pixel over the sweep, and the
    templates' relative error ε it stands for (``χ² = dof + ε² Σ(m/σ)²``)."""

    status: str
    reasons: tuple[str, ...]
    chi2_per_pixel: float
    model_error: float
    unexplained_positions: tuple[int, ...]
    positions: int
    allowance: float
    inside_outside: tuple[float, float] | None = None  # ε between the fits' positions, and beyond them
    position_errors: tuple[float, ...] = ()  # ε at each position

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def reason(self) -> str:
        return "; ".join(self.reasons)

    def record(self) -> dict:
        """The light model's ``quality``."""
        out: dict = {"status": self.status}
        if self.reasons:
            out["reason"] = self.reason
        return out | {
            "model_error": round(self.model_error, 5),
            "model_error_allowance": self.allowance,
            "chi2_per_pixel": round(self.chi2_per_pixel, 5),
            "positions": self.positions,
            "unexplained_positions": list(self.unexplained_positions),
            **(
                {
                    "model_error_inside": round(self.inside_outside[0], 5),
                    "model_error_outside": round(self.inside_outside[1], 5),
                }
                if self.inside_outside is not None
                else {}
            ),
            "model_error_per_position": list(self.position_errors),
        }

    def line(self) -> str:
        """One line, as the command line and the job's note say it."""
        if self.ok:
            return (
                f"quality ok: the templates explain the sweep to {100 * self.model_error:.1f} % of its light "
                f"(χ²/pixel {self.chi2_per_pixel:.3f})"
            )
        return f"quality SUSPECT: {self.reason}"


@dataclass
class ProcessReport:
    """What :func:`process_run` did and wrote.

    ``outputs`` maps a kind (``exr``, ``png``, ``ies``, ``ldt``, ``tm25``, ``report``) to
    its files; ``timings`` the stages (``noise``, ``layout``, ``camera``, ``positions``,
    ``sources``, ``fit``, ``exports``, ``report``, ``total``) to seconds of wall time;
    ``task_stages`` the seconds the position tasks spent in each of their stages (``read``,
    ``merge``, ``encode``, ``write`` (the position file), ``images``, ``masks``,
    ``sources``), summed over the tasks, wherever they ran.
    """

    run_file: Path
    results_file: Path
    positions: int
    noise: NoiseModel
    outputs: dict[str, list[Path]] = field(default_factory=dict)
    samples: object = None
    model: object = None
    saturated_pixels: int = 0
    light_model: Path | None = None
    estimator: str = ""
    estimator_reason: str = ""
    layout_search: str = ""  # how the sources were found in the data (empty when a layout was given)
    aperture_fit: FittedNumber | None = None  # the aperture's diameter fitted to the data, or why that failed
    sensor_distance_fit: FittedNumber | None = None  # the sensor distance fitted to the data
    rig_calibration: RigCalibration | None = None  # the rig fitted to the data (self-calibration)
    point_spread: dict[str, Any] | None = None  # the measured point spread, where the rig's camera has one
    point_spread_refinement: dict[str, Any] | None = None  # the point spread refined from the sweep, where tried
    quality: Quality | None = None  # the verdict on the light model
    spatial_resolution_m: float = float("nan")
    n_positions: int = 0
    partial: bool = False
    compute: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    task_stages: dict[str, float] = field(default_factory=dict)
    skipped_corrupt: list[CorruptFrame] = field(default_factory=list)  # --ignore-corrupt: the frames skipped

    def add_task(self, result: PositionResult) -> None:
        for stage, seconds in result.stages.items():
            self.task_stages[stage] = self.task_stages.get(stage, 0.0) + seconds
        self.task_stages["tasks"] = self.task_stages.get("tasks", 0.0) + result.seconds

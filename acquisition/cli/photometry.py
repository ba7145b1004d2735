"""``mirrorgonio calibrate-photometry``: the camera's photometric scale from a reference, stored
in the rig file (``docs/lab-guide.md``, "Absolute photometry")."""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from acquisition.cli.app import app, domain_errors, fail

if TYPE_CHECKING:
    from processing import LampReference, MeterReference


def _point(text: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(part) for part in text.split(","))
    except ValueError:
        raise fail(f"--meter-at: three numbers X,Y,Z in metres (got {text!r})") from None
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise fail(f"--meter-at: finite numbers (got {text!r})")
    return x, y, z


def _reference(
    uncertainty: float,
    lamp: tuple[float | None, float, float, str | None],
    meter: tuple[float | None, str | None, float],
    name: str | None,
) -> LampReference | MeterReference:
    """The one reference the options give (a lamp's certificate or a meter's reading), or a
    one-line error naming the option."""
    from processing import LampReference, MeterReference

    candela, theta, phi, source = lamp
    lux, meter_at, position_uncertainty = meter
    if (candela is None) == (lux is None):
        raise fail(
            "--reference-cd or --illuminance-lux: give one reference (a lamp's certificate or a meter's reading)"
        )
    if candela is not None:
        if meter_at is not None:
            raise fail("--meter-at: only with --illuminance-lux")
        angles = math.radians(theta), math.radians(phi)
        return LampReference(candela, uncertainty, *angles, source, name or "reference lamp")
    if meter_at is None:
        raise fail("--meter-at: where the meter read --illuminance-lux (X,Y,Z in metres of the light frame)")
    assert lux is not None  # one of the two, checked above
    return MeterReference(lux, uncertainty, _point(meter_at), position_uncertainty, name or "illuminance meter")


@app.command("calibrate-photometry")
def calibrate_photometry(
    light_model: Annotated[
        Path,
        typer.Argument(
            help="The light model (RUN.light.json) of the reference lamp's run, or of the light the meter read."
        ),
    ],
    rig: Annotated[
        Path,
        typer.Option("--rig", help="The rig file the scale is written into, as its \\[camera.photometric] table."),
    ],
    reference_uncertainty: Annotated[
        float,
        typer.Option(
            "--reference-uncertainty",
            min=0.0,
            max=0.5,
            help="The reference's own 1σ, a fraction (a certificate's 1.5 % at k=2 is 0.0075).",
        ),
    ],
    reference_cd: Annotated[
        float | None,
        typer.Option(
            "--reference-cd", min=0.0, help="The reference lamp's luminous intensity (cd), its certificate's."
        ),
    ] = None,
    theta: Annotated[
        float, typer.Option("--theta-deg", min=0.0, max=90.0, help="The certificate's direction: θ in the light frame.")
    ] = 0.0,
    phi: Annotated[float, typer.Option("--phi-deg", min=-360.0, max=360.0, help="... and φ.")] = 0.0,
    source: Annotated[
        str | None, typer.Option("--source", help="The lamp's source in the model (default: the one holding the flux).")
    ] = None,
    illuminance_lux: Annotated[
        float | None,
        typer.Option("--illuminance-lux", min=0.0, help="An illuminance meter's reading (lx) in front of the light."),
    ] = None,
    meter_at: Annotated[
        str | None,
        typer.Option("--meter-at", help="Where the meter's head was: X,Y,Z in metres of the light frame, facing it."),
    ] = None,
    position_uncertainty: Annotated[
        float, typer.Option("--position-uncertainty-m", min=0.0, max=0.1, help="The meter's placing, 1σ (m).")
    ] = 0.001,
    name: Annotated[
        str | None, typer.Option("--reference-name", help="What the reference was (its make and serial number).")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the calibration as JSON only.")] = False,
) -> None:
    """The camera's photometric scale (candela per unit of the light model) from a reference
    lamp of known luminous intensity swept on the rig, or from an illuminance meter's reading
    at a known point in front of a light; written into the rig file, after which the runs it
    takes are processed in candela and lumens."""
    from drivers.contracts.rig import RigError, load_rig
    from drivers.contracts.rig_edits import store_photometric_calibration
    from processing import LightModel, LightModelError, PhotometryError
    from processing import calibrate_photometry as calibrate

    reference = _reference(
        reference_uncertainty,
        (reference_cd, theta, phi, source),
        (illuminance_lux, meter_at, position_uncertainty),
        name,
    )
    try:
        load_rig(rig)  # a rig file that cannot take the scale is refused before any work
        model = LightModel.load(light_model)
        made = datetime.now(UTC).isoformat(timespec="seconds")
        calibration = calibrate(model, reference, run_id=model.provenance.get("run_id"), made_utc=made)
        store_photometric_calibration(rig, calibration)
    except domain_errors(PhotometryError, LightModelError, RigError) as exc:
        raise fail(str(exc)) from None
    if as_json:
        typer.echo(json.dumps(calibration.model_dump(mode="json")))
        return
    typer.echo(
        f"{calibration.candela_per_unit:.6g} cd per unit ± {100 * calibration.relative_uncertainty:.2f} % (1σ), "
        f"from {calibration.reference}"
    )
    typer.echo(f"written to {rig} as [camera.photometric]: runs taken with it are processed in candela and lumens")

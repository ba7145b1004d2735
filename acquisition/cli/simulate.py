"""``mirrorgonio simulate``: the simulated arm's Modbus server, one rendered capture, a measured
point spread."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from acquisition.cli.app import (
    RigOption,
    default_rig,
    domain_errors,
    fail,
    simulate_app,
)

if TYPE_CHECKING:
    from drivers.camera import RawFrame


# --- simulate -----------------------------------------------------------------------------
@simulate_app.command("arm")
def simulate_arm(
    port: Annotated[int, typer.Option(help="TCP port of the Modbus server.")] = 5020,
    host: Annotated[str, typer.Option(help="Address to listen on (loopback by default).")] = "127.0.0.1",
    speed: Annotated[
        float | None, typer.Option(help="Linear speed in m/s (inf: instantaneous moves); default 0.05.")
    ] = None,
    accel: Annotated[float | None, typer.Option(help="Linear acceleration in m/s^2; default 0.5.")] = None,
    angular_speed: Annotated[
        float | None, typer.Option("--angular-speed", help="Angular speed in rad/s; default 1.")
    ] = None,
) -> None:
    """Serve the simulated stage as a Modbus TCP server until interrupted (Ctrl-C or SIGTERM)."""
    import signal

    from sim_devices.modbus_server import serve
    from sim_devices.stage import StageConfig

    mechanics: dict = {}
    for name, value in (("speed", speed), ("accel", accel), ("angular-speed", angular_speed)):
        if value is not None and not value > 0:
            raise fail(f"--{name}: must be positive, got {value}")
    if speed is not None:
        mechanics.update(speed_m_s=speed, accel_m_s2=math.inf if math.isinf(speed) else (accel or 10 * speed))
    elif accel is not None:
        mechanics.update(accel_m_s2=accel)
    if angular_speed is not None:
        mechanics.update(angular_speed_rad_s=angular_speed, angular_accel_rad_s2=10 * angular_speed)

    def _terminated(signum, frame):  # a container's stop: leave as on Ctrl-C, closing the server
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminated)
    typer.echo(f"simulated arm: Modbus TCP on {host}:{port} (Ctrl-C to stop)")
    try:
        serve(port=port, host=host, stage_config=StageConfig(**mechanics))
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        raise fail(f"simulated arm: cannot listen on {host}:{port}: {exc.strerror or exc}") from None


def _capture_one(
    rig_path: Path,
    position: int,
    exposure: float,
    output: Path,
    truth: str | None,
    noise: bool,
    diffraction: bool,
    seed: int | None,
) -> RawFrame:
    from drivers.contracts.rig import load_rig
    from drivers.pose import Pose
    from sim_devices.camera import SimulatedCamera
    from sim_devices.lights import load_truth
    from sim_devices.world import SimWorld

    rig = load_rig(rig_path)
    tool_poses = rig.tool_poses()
    if not 0 <= position < len(tool_poses):
        raise fail(f"--position: {position} is outside the schedule (0..{len(tool_poses) - 1})")
    if not exposure > 0 or not math.isfinite(exposure):
        raise fail(f"--exposure: must be a positive number of seconds, got {exposure}")
    tool: Pose = tool_poses[position]
    world = SimWorld(lambda: tool, rig.light.light_to_tool.to_pose(), arm_base=rig.arm.base.to_pose())
    camera = SimulatedCamera(
        rig,
        world,
        output.parent,
        truth=load_truth(truth) if truth else None,
        noise=noise,
        diffraction=diffraction,
        seed=seed,
        source=str(rig_path),
    )
    return camera.capture_to(output, exposure)


@simulate_app.command("capture")
def simulate_capture(
    output: Annotated[Path, typer.Option("-o", "--output", help="DNG file to write.")],
    rig: RigOption = None,
    position: Annotated[int, typer.Option(help="Schedule position index.")] = 0,
    exposure: Annotated[float, typer.Option(help="Exposure time in seconds.")] = 0.01,
    truth: Annotated[
        str | None, typer.Option(help="Truth light (shipped name or TOML path); default from the rig.")
    ] = None,
    noise: Annotated[bool, typer.Option(help="Photon and read noise.")] = True,
    diffraction: Annotated[bool, typer.Option(help="Airy diffraction of the aperture.")] = True,
    seed: Annotated[int | None, typer.Option(help="Random seed; default from the rig.")] = None,
) -> None:
    """Render one frame of the mirrored ball and write it as a DNG file."""
    try:
        frame = _capture_one(rig or default_rig(), position, exposure, output, truth, noise, diffraction, seed)
    except domain_errors() as exc:
        raise fail(str(exc)) from None
    typer.echo(
        f"wrote {output} ({frame.mosaic.shape[1]}x{frame.mosaic.shape[0]}, {frame.cfa_pattern}, "
        f"exposure {frame.exposure_s:g} s, max {int(frame.mosaic.max())} DN)"
    )


@simulate_app.command("certificate")
def simulate_certificate(
    truth: Annotated[str, typer.Argument(help="Truth light (shipped name or TOML path), e.g. reference-lamp.")],
    rig: RigOption = None,
    theta: Annotated[float, typer.Option("--theta-deg", min=0.0, max=90.0, help="Polar angle, degrees.")] = 0.0,
    phi: Annotated[float, typer.Option("--phi-deg", min=-360.0, max=360.0, help="Azimuth, degrees.")] = 0.0,
) -> None:
    """Print each emitter's luminous intensity (cd) in one direction: a simulated reference
    lamp's calibration certificate, for ``mirrorgonio calibrate-photometry --reference-cd``."""
    from drivers.contracts.rig import load_rig
    from sim_devices.lights import TruthError, load_truth

    try:
        camera = load_rig(rig or default_rig()).camera
        light = load_truth(truth)
        values = [
            (e.name, float(e.luminous_intensity_cd(math.radians(theta), math.radians(phi), camera)))
            for e in light.emitters
        ]
    except domain_errors(TruthError) as exc:
        raise fail(str(exc)) from None
    for name, candela in values:
        typer.echo(f"{name}: {candela:.6g} cd at theta {theta:g} deg, phi {phi:g} deg")


@simulate_app.command("point-spread")
def simulate_point_spread(
    output: Annotated[Path, typer.Option("-o", "--output", help="The .npz file to write.")],
    distance: Annotated[
        float, typer.Option(min=1e-3, help="The LED's distance in front of the pinhole (m); about the light's image's.")
    ],
    rig: RigOption = None,
    side: Annotated[int, typer.Option(min=11, max=1025, help="Pixels a side.")] = 129,
    peak_electrons: Annotated[
        float | None, typer.Option(min=1.0, help="The brightest pixel's electrons, with photon and read noise.")
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed of the noise.")] = 0,
) -> None:
    """Image a small LED through the rig's simulated pinhole (its Fresnel point spread, each
    channel's band), as a lab measures its camera's point spread for the rig's
    camera.measured_point_spread table."""
    import numpy as np

    from drivers.contracts.rig import load_rig
    from sim_devices.optics.point_spread import led_point_spread

    try:
        camera = load_rig(rig or default_rig()).camera
        psf = led_point_spread(camera, distance, side | 1, peak_electrons, seed)
        np.savez(output, psf=psf, distance_m=distance, pixel_pitch_m=camera.pixel_pitch_m)
    except domain_errors() as exc:
        raise fail(str(exc)) from None
    typer.echo(f"wrote {output} ({psf.shape[2]}x{psf.shape[1]} px a channel, the LED {1e3 * distance:g} mm away)")

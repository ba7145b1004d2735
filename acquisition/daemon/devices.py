"""Build the arm, the camera and the light switch the configuration names.

The daemon knows devices only through the :mod:`drivers` interfaces; this module is the
one place that turns configuration into concrete objects, the simulated rig included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from acquisition.daemon.settings import DaemonSettings, SettingsError
from drivers.arm import Arm
from drivers.camera import Camera
from drivers.contracts.rig import Rig, load_rig
from drivers.folder_camera import FolderCamera
from drivers.gphoto2_camera import Gphoto2Camera
from drivers.light import SWEEP, LightSwitch, ManualLightSwitch, NoLightSwitch
from drivers.modbus_arm import ModbusArm
from drivers.modbus_profile import SIM_STAGE_PROFILE, load_profile
from drivers.serial_arm import MelfaSerialArm
from sim_devices.camera import ROOM_RADIANCE, SimulatedCamera, require_render_memory
from sim_devices.lights import load_truth
from sim_devices.world import SimulatedLightSwitch, SimWorld


@dataclass
class Devices:
    """The devices of one rig, and what must be stopped when the daemon exits.

    Without a ``light`` switch the runs take no calibration frames.
    """

    arm: Arm
    camera: Camera
    simulated: dict = field(default_factory=dict)  # the simulated parts, for tests and health
    _closers: list = field(default_factory=list)
    light: LightSwitch = field(default_factory=NoLightSwitch)

    def close(self) -> None:
        for closer in reversed(self._closers):
            try:
                closer()
            except Exception:  # noqa: BLE001 - best effort at shutdown; each closer is independent
                pass
        self._closers.clear()


def check_configured_files(settings: DaemonSettings) -> None:
    """Read the files the configuration names (the rig, the arm's profile, the simulated
    camera's truth) and check that the simulated camera's frames fit in memory, as
    :func:`open_devices` will: ``mirrorgonio serve`` calls it before the server starts, so a
    bad file ends the start with one line (inside the server's startup it came with a
    traceback).

    Raises
    ------
    RigError, ProfileError, TruthError
        One line naming the file and, where there is one, the field.
    """
    rig = load_rig(settings.rig)
    if settings.arm.kind in ("modbus-tcp", "modbus-rtu") and settings.arm.profile is not None:
        load_profile(settings.arm.profile)
    if settings.camera.kind == "simulated":
        if settings.camera.simulated.truth:
            load_truth(settings.camera.simulated.truth)
        require_render_memory(rig, str(settings.rig))


def open_devices(settings: DaemonSettings, rig: Rig) -> Devices:
    """Create, start and connect the configured arm, camera and light switch."""
    closers: list = []
    simulated: dict = {}
    try:
        arm = _open_arm(settings, rig, closers, simulated)
        camera = _open_camera(settings, rig, simulated, arm)
        camera.connect()
        closers.append(camera.close)
        light = _open_light(settings, simulated)
    except BaseException:
        for closer in reversed(closers):
            closer()
        raise
    return Devices(arm=arm, camera=camera, simulated=simulated, _closers=closers, light=light)


def _open_light(settings: DaemonSettings, simulated: dict) -> LightSwitch:
    """The light switch: the simulated world's with the simulated camera, manual with any other
    unless the settings name one."""
    kind = settings.light.kind or ("simulated" if "world" in simulated else "manual")
    if kind == "simulated":
        if "world" not in simulated:
            raise SettingsError("light.kind: the simulated light switch needs the simulated camera (camera.kind)")
        switch: LightSwitch = SimulatedLightSwitch(simulated["world"])
        simulated["light"] = switch
        return switch
    if kind == "manual":
        return ManualLightSwitch()
    return NoLightSwitch()


def _open_arm(settings: DaemonSettings, rig: Rig, closers: list, simulated: dict) -> Arm:
    cfg = settings.arm
    limits = rig.soft_limits()
    if cfg.kind == "simulated":
        from sim_devices.modbus_server import SimulatedModbusArm  # noqa: PLC0415 - heavy: pymodbus's server
        from sim_devices.stage import SimulatedStage, StageConfig  # noqa: PLC0415 - heavy: scipy.spatial.transform

        stage = SimulatedStage(
            StageConfig(
                speed_m_s=cfg.simulated.speed_m_s,
                accel_m_s2=cfg.simulated.accel_m_s2 if math.isfinite(cfg.simulated.speed_m_s) else math.inf,
                angular_speed_rad_s=cfg.simulated.angular_speed_rad_s,
                angular_accel_rad_s2=10 * cfg.simulated.angular_speed_rad_s,
            )
        )
        server = SimulatedModbusArm(stage, host="127.0.0.1", port=cfg.port)
        server.start()
        closers.append(server.stop)
        simulated.update(stage=stage, modbus_server=server)
        arm: Arm = ModbusArm(
            SIM_STAGE_PROFILE,
            host="127.0.0.1",
            port=server.port,
            limits=limits,
            timeout_s=cfg.timeout_s,
            retries=cfg.retries,
        )
    elif cfg.kind in ("modbus-tcp", "modbus-rtu"):
        if cfg.profile is None:
            raise SettingsError("arm.profile: a Modbus arm needs its register-map profile")
        if cfg.kind == "modbus-tcp":
            arm = ModbusArm(
                cfg.profile,
                transport="tcp",
                host=cfg.host,
                port=cfg.port or 502,
                limits=limits,
                timeout_s=cfg.timeout_s,
                retries=cfg.retries,
            )
        else:
            if not cfg.serial_port:
                raise SettingsError("arm.serial_port: Modbus RTU needs a serial port")
            arm = ModbusArm(
                cfg.profile,
                transport="rtu",
                serial_port=cfg.serial_port,
                baudrate=cfg.baudrate or 19200,
                limits=limits,
                timeout_s=cfg.timeout_s,
                retries=cfg.retries,
            )
    else:
        if not cfg.serial_port:
            raise SettingsError("arm.serial_port: a serial arm needs a serial port")
        arm = MelfaSerialArm(
            cfg.serial_port, baudrate=cfg.baudrate or 9600, timeout_s=cfg.timeout_s, retries=cfg.retries, limits=limits
        )
    arm.connect()
    closers.append(arm.close)
    return arm


def _open_camera(settings: DaemonSettings, rig: Rig, simulated: dict, arm: Arm) -> Camera:
    cfg = settings.camera
    spool = Path(settings.data_dir) / "spool"
    if cfg.kind == "simulated":
        light_to_tool, base = rig.light.light_to_tool.to_pose(), rig.arm.base.to_pose()
        lights = {"light_on": SWEEP.light_on, "room_lit": SWEEP.room_lit}  # the lab as a sweep needs it
        if "stage" in simulated:  # the simulated stage in this process: its true pose
            world = SimWorld(simulated["stage"].true_pose, light_to_tool, arm_base=base, **lights)
        else:
            # Any other arm (the simulated arm in its own process or container, or a real
            # one): the light is where the arm's controller says the tool is.
            world = SimWorld.following(arm.position, light_to_tool, arm_base=base, **lights)
        sim = cfg.simulated
        camera = SimulatedCamera(
            rig,
            world,
            spool,
            truth=load_truth(sim.truth) if sim.truth else None,
            noise=sim.noise,
            diffraction=sim.diffraction,
            latency_s=sim.latency_s,
            environment_radiance=ROOM_RADIANCE if sim.room_radiance is None else sim.room_radiance,
            source=str(settings.rig),
        )
        simulated["world"] = world
        return camera
    if cfg.kind == "folder":
        if cfg.folder is None:
            raise SettingsError("camera.folder: a folder camera needs the folder to watch")
        return FolderCamera(cfg.folder, timeout_s=cfg.capture_timeout_s)
    return Gphoto2Camera(port=cfg.gphoto2_port, model=cfg.gphoto2_model, download_dir=spool)

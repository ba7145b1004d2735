"""The simulated camera: renders the mirrored ball (or the rig's object), writes a real DNG,
decodes it back.

Every frame goes through the same decode path as a real camera's raw file
(:func:`drivers.raw_decode.decode_raw`), so the acquisition cannot tell the difference.
The light's pose, and whether the light and the room are lit, come from the shared
:class:`~sim_devices.world.SimWorld`: the light's emitters are rendered only while it shines,
the room (a uniform environment the ball reflects) only while it is lit. With both dark a
frame is the sensor's bias and read noise.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from drivers.camera import Camera, RawFrame
from drivers.config_files import require_memory
from drivers.contracts.rig import Rig, RigError
from drivers.errors import DeviceError
from drivers.raw_decode import decode_raw
from sim_devices.colour import colour_matrices
from sim_devices.dng import write_dng
from sim_devices.lights import TruthLight, load_truth
from sim_devices.optics import MirrorBallRenderer, Rendering
from sim_devices.sensor import SensorModel
from sim_devices.world import SimWorld

if TYPE_CHECKING:
    from sim_devices.object_scene import ObjectSceneRenderer

#: The simulated lab's room radiance when its lights are on (the daemon's simulated camera).
#: The ball's brightest pixels then gather about 99 000 e⁻/s with the default optics (a
#: chrome ball reflects 55 % at normal incidence; sensitivity 1000 e⁻/s per unit radiance):
#: at the daemon's default ambient bracket (10, 40 and 160 ms) 5, 20 and 79 % of the full
#: well, the longest frame well exposed and unclipped.
ROOM_RADIANCE = 180.0
#: The memory one rendered frame takes at its peak, per sensor pixel, in bytes: the default
#: rig's capture (2000 × 1312 px) peaks 435 MB above the program's own, 166 B a pixel; the
#: rest is a margin for the object scene and the Fresnel point spread.
RENDER_BYTES_PER_PIXEL = 256


def require_render_memory(rig: Rig, source: str = "rig") -> None:
    """Refuse a rig whose frames cannot be rendered in the memory available, before any array
    is allocated: a :class:`~drivers.contracts.rig.RigError` naming ``source`` (the rig's
    file) and ``camera.width × camera.height`` (:func:`drivers.config_files.require_memory`)."""
    cam = rig.camera
    require_memory(
        cam.width * cam.height * RENDER_BYTES_PER_PIXEL,
        f"{source}: camera.width × camera.height",
        f"rendering a {cam.width} × {cam.height} px frame",
        RigError,
    )


class SimulatedCamera(Camera):
    """A pinhole (or thin-lens) camera looking at the mirrored ball, or at the rig's object.

    With ``rig.object`` set the scene is that mesh lit by the truth light
    (:class:`~sim_devices.object_scene.ObjectSceneRenderer`, reflectance from
    ``rig.simulation.surface``); ``renderer_options`` go to whichever renderer is used.

    Parameters
    ----------
    rig : Rig
        Camera, ball and light geometry; ``rig.simulation`` gives the truth, seed,
        noise and diffraction switches and the point spread unless overridden here.
    world : SimWorld
        Where the light is at the moment of capture.
    out_dir : path
        Folder the DNG files are written to (injected: tests use a temporary folder).
    truth : TruthLight, optional
        Overrides ``rig.simulation.truth``.
    point_spread : {"geometric-airy", "fresnel"}, optional
        Overrides ``rig.camera.point_spread`` (the mirrored ball only).
    wall_clock : callable
        Seconds since the epoch, for the frames' timestamps.
    latency_s : float
        Time a capture takes beyond the exposure (0 for benchmarks).
    environment_radiance : float or (R, G, B)
        Uniform radiance of the room the ball reflects while the world's room is lit (0, a
        dark room, by default; :data:`ROOM_RADIANCE` for the daemon's simulated lab): a
        calibration frame shows the ball as a bright disc against a dark background.
        Settable later, as is ``light_on`` (the world's: False, the light's emitters are
        dark, its housing still in place), for taking a calibration frame between runs.
    """

    def __init__(
        self,
        rig: Rig,
        world: SimWorld,
        out_dir: str | Path,
        *,
        truth: TruthLight | None = None,
        noise: bool | None = None,
        diffraction: bool | None = None,
        point_spread: str | None = None,
        seed: int | None = None,
        renderer_options: dict | None = None,
        wall_clock: Callable[[], float] = time.time,
        sleep: Callable[[float], None] = time.sleep,
        latency_s: float = 0.0,
        serial: str = "SIM-0001",
        environment_radiance: float | tuple[float, float, float] = 0.0,
        source: str = "rig",
    ):
        require_render_memory(rig, source)
        sim = rig.simulation
        self.rig = rig
        self.world = world
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        # Emitters given by a colour temperature are seen through this camera's channels.
        self.truth = (truth or load_truth(sim.truth)).seen_by(rig.camera)
        seed = sim.seed if seed is None else seed
        # The rig's object, when it has one, is photographed instead of the ball.
        options = dict(renderer_options or {})
        renderer_class: type[MirrorBallRenderer] | type[ObjectSceneRenderer]
        if rig.object is None:
            renderer_class = MirrorBallRenderer
            options.setdefault("point_spread", rig.camera.point_spread if point_spread is None else point_spread)
        else:
            from sim_devices.object_scene import ObjectSceneRenderer  # noqa: PLC0415 - heavy: trimesh, for an object

            renderer_class = ObjectSceneRenderer
        self.renderer = renderer_class(
            rig,
            self.truth,
            diffraction=sim.diffraction if diffraction is None else diffraction,
            seed=seed,
            environment_radiance=environment_radiance,
            **options,
        )
        self.sensor = SensorModel.from_rig(rig.camera, noise=sim.noise if noise is None else noise)
        self.rng = np.random.default_rng(seed + 1)
        self.name = "simulated pinhole camera"
        self.serial = serial
        self._wall_clock = wall_clock
        self._sleep = sleep
        self.latency_s = latency_s
        self._counter = itertools.count()
        # The last rendering of each state of the lights, with the pose it is for: calibration
        # frames (the light off) between sweeps do not throw away the sweep's rendering.
        self._cached: dict[tuple[bool, bool], tuple[tuple, Rendering]] = {}
        self._room = self.renderer.environment.copy()
        self._colour: dict | None = None

    @property
    def environment_radiance(self) -> np.ndarray:
        """The room's radiance (R, G, B) while it is lit."""
        return self._room.copy()

    @environment_radiance.setter
    def environment_radiance(self, value: float | tuple[float, float, float]) -> None:
        self.renderer.set_environment(value)  # checked there
        self._room = self.renderer.environment.copy()
        self._cached.clear()

    @property
    def light_on(self) -> bool:
        """Whether the light shines (the world's state, shared with its light switch)."""
        return self.world.light_on

    @light_on.setter
    def light_on(self, value: bool) -> None:
        self.world.light_on = bool(value)

    @property
    def identity(self) -> str:
        return f"mirrorgonio {self.name} {self.serial}"

    def rendering(self) -> Rendering:
        """The noise-free expected electron rates for the light's current pose and the lights' state."""
        pose = self.world.light_pose()
        lights = (self.world.light_on, self.world.room_lit)
        key = tuple(round(v, 10) for v in pose.as_tuple())
        cached = self._cached.get(lights)
        if cached is None or cached[0] != key:
            self.renderer.truth = self.truth if lights[0] else None
            self.renderer.set_environment(self._room if lights[1] else 0.0)
            cached = (key, self.renderer.render(pose))
            self._cached[lights] = cached
        return cached[1]

    def capture(self, exposure_s: float) -> RawFrame:
        return self.capture_to(self.out_dir / f"sim-{next(self._counter):06d}.dng", exposure_s)

    def capture_to(self, path: str | Path, exposure_s: float) -> RawFrame:
        """Capture one frame into the DNG file ``path`` and decode it back."""
        if not exposure_s > 0:
            raise DeviceError(self.identity, "capture", f"exposure must be positive, got {exposure_s!r}")
        rates = self.rendering().rate
        mosaic = self.sensor.expose(rates, exposure_s, self.rng)
        self.last_mosaic = mosaic  # what was written, for checking the decode path
        if self.latency_s:
            self._sleep(self.latency_s + exposure_s)
        timestamp = self._wall_clock()
        cam = self.rig.camera
        write_dng(
            path,
            mosaic,
            cfa_pattern=cam.cfa_pattern,
            black_level=cam.black_level_dn,
            white_level=cam.white_level,
            bits_per_sample=cam.bit_depth,
            exposure_s=exposure_s,
            camera_model=self.name,
            serial=self.serial,
            timestamp=timestamp,
            colour=self.colour_matrices,
        )
        return decode_raw(path)

    @property
    def colour_matrices(self) -> dict:
        """The DNG colour matrices of this camera's channels (:func:`sim_devices.colour.colour_matrices`),
        derived on the first capture (colour-science takes a second to import)."""
        if self._colour is None:
            self._colour = colour_matrices(self.rig.camera)
        return self._colour

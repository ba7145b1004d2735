"""``mirrorgonio bench hdr``: this project's raw HDR merge next to its peers, on the same brackets.

The scene
    The simulated rig's mirrored ball (the rig's truth light, rendered by
    :class:`sim_devices.optics.MirrorBallRenderer` at a few distinct schedule positions and
    cycled over the benchmark's positions) plus a smooth background of log-uniform
    brightness: a horizontal gradient from 1e2 to 1e7 e⁻/s, the same in every channel, so
    that the whole dynamic range of the bracket is exercised (the ball image alone is
    mostly dark with a few very bright sources). Each position's bracket is exposed by
    :class:`sim_devices.sensor.SensorModel` (photon and read noise, full-well clipping) with
    fresh seeded noise, outside the timed sections; only one bracket is held at a time.

The methods, given the same frames
    * ``mirrorgonio_optimal`` / ``mirrorgonio_poisson``: :func:`processing.hdr.brackets.merge_raw` on
      the raw uint16 mosaic (black level and saturation handled inside, the rig's noise
      model).
    * ``hdrutils``: HDRutils' Poisson merge of raw mosaics (``merge.imread_merge_demosaic``,
      which ``HDRutils.merge(..., demosaic_first=False)`` calls). HDRutils offers no
      in-memory entry point, only file names that it reads with rawpy or imageio; its own
      merge loop is called with the frames served from memory by replacing the module's
      ``io`` reader (and its ``tqdm`` progress bar) for the call. It always demosaics its
      merged mosaic (bilinear) before returning; that time is measured separately and the
      merge-only time is what the speed-up is computed against (in its favour).
    * ``colour_hdri``: ``colour_hdri.image_stack_to_HDRI`` with its default Debevec weights on
      single-channel images of the black-subtracted mosaic normalised to [0, 1], stacked
      from the shortest exposure to the longest (its clipping fix assumes that order).
    * ``opencv_debevec``: ``cv2.createMergeDebevec().process`` on uint16 single-channel
      images, black removed (negatives clipped to 0) and scaled to the full 16-bit range,
      since its hat weights and linear-response look-up table span 0..65535.
      ``opencv_debevec_12bit`` gives it the same signal unscaled (12-bit values in 16-bit
      images), as a user would without reading its source: its weights then never reach
      zero at the sensor's clipping level.

    Preparing a peer's input (type conversion, black subtraction, normalisation, building a
    colour-hdri ``ImageStack``) is not timed; this project's merge takes the raw frames and
    its time includes all of that.

The error
    Every output is converted to DN/s above black on the mosaic (each photosite's own
    channel for the peers that return RGB; the scales are exact, nothing is fitted) and
    compared with the truth on the same pixel set for every method: photosites whose true
    signal in the shortest exposure stays 3 σ below the clipping level and that reach at
    least 10 DN in the longest.
"""

from __future__ import annotations

import importlib
import math
import os
import statistics
import time
import types
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

BACKGROUND_E_PER_S = (1e2, 1e7)
SHORTEST_S, LONGEST_S = 1e-3, 0.5
MIN_DN_LONGEST = 10.0
CLIP_MARGIN_SIGMA = 3.0
DISTINCT_SCENES = 6
TARGET_SPEEDUP = 3.0
OURS = ("mirrorgonio_optimal", "mirrorgonio_poisson")
PEERS = ("hdrutils", "colour_hdri", "opencv_debevec", "opencv_debevec_12bit")
PEER_EXTRA = "not installed (pip install 'mirrorgonio[bench]')"


class BenchmarkError(ValueError):
    """Parameters the benchmark cannot run with (one line naming the field)."""


# --- the scene -----------------------------------------------------------------------------------
@dataclass
class _Sensor:
    cfa_pattern: str
    black: int
    white: int
    gain: float  # e⁻/DN
    read_dn: float
    model: object  # sim_devices.sensor.SensorModel

    @property
    def range_dn(self) -> float:
        return float(self.white - self.black)

    def variance_dn(self, mean_dn):
        return np.maximum(mean_dn, 0.0) / self.gain + self.read_dn**2 + 1.0 / 12.0


@dataclass
class _Scene:
    position: int
    rate_e: np.ndarray  # (H, W) e⁻/s on the mosaic
    mask: np.ndarray  # the pixel set
    truth: np.ndarray  # true DN/s above black on the pixel set
    floor_rel_var_sum: float  # Σ over the set of the ideal merge's variance / truth²


def exposure_times(count: int) -> np.ndarray:
    """``count`` exposures, geometric from SHORTEST_S to LONGEST_S."""
    if count == 1:
        return np.array([SHORTEST_S])
    return SHORTEST_S * (LONGEST_S / SHORTEST_S) ** (np.arange(count) / (count - 1))


def _rig_at_size(rig, width: int, height: int):
    """The rig with its sensor resampled to ``width`` x ``height``, the same field of view across."""
    from drivers.contracts.rig import rig_from_dict, rig_to_toml_dict

    cam = rig.camera
    if (cam.width, cam.height) == (width, height):
        return rig
    scale = cam.width / width
    data = rig_to_toml_dict(rig)
    data["camera"].update(width=width, height=height, pixel_pitch_m=cam.pixel_pitch_m * scale)
    if cam.principal_point_px is not None:
        cx, cy = cam.principal_point_px
        data["camera"]["principal_point_px"] = [(cx + 0.5) / scale - 0.5, (cy + 0.5) / scale - 0.5]
    return rig_from_dict(data, f"rig {rig.name!r} at {width}x{height}")


def _background(height: int, width: int) -> np.ndarray:
    lo, hi = BACKGROUND_E_PER_S
    return np.broadcast_to(np.logspace(math.log10(lo), math.log10(hi), width), (height, width))


def _pixel_set(truth_dn: np.ndarray, sensor: _Sensor, exposures: np.ndarray):
    """The compared photosites, and the variance of the ideal merge of each."""
    clip = sensor.range_dn
    short = truth_dn * exposures.min()
    unsaturated = short + CLIP_MARGIN_SIGMA * np.sqrt(sensor.variance_dn(short)) < clip
    mask = unsaturated & (truth_dn * exposures.max() >= MIN_DN_LONGEST)
    # Off the frame's outer row and column: HDRutils' bilinear demosaic (edge-repeating
    # convolution) changes the sampled channel's value there, which is not its merge's doing.
    mask[0, :] = mask[-1, :] = mask[:, 0] = mask[:, -1] = False
    x = truth_dn[mask]
    info = np.zeros_like(x)
    for t in exposures:
        mu = x * t
        var = sensor.variance_dn(mu)
        usable = mu + CLIP_MARGIN_SIGMA * np.sqrt(var) < clip
        info += np.where(usable, t * t / var, 0.0)
    return mask, x, float(np.sum(1.0 / (info * x * x)))


def _scenes(rig, sensor: _Sensor, exposures: np.ndarray, distinct: int, seed: int) -> list[_Scene]:
    from sim_devices.lights import load_truth
    from sim_devices.optics import MirrorBallRenderer
    from sim_devices.sensor import mosaic_of

    renderer = MirrorBallRenderer(
        rig, load_truth(rig.simulation.truth), diffraction=rig.simulation.diffraction, seed=seed
    )
    poses = rig.light_poses()
    picks = sorted({int(i) for i in np.linspace(0, len(poses) - 1, distinct).round()})
    background = _background(rig.camera.height, rig.camera.width)
    scenes = []
    for i in picks:
        rate = mosaic_of(renderer.render(poses[i]).rate, sensor.cfa_pattern) + background
        mask, truth, floor = _pixel_set(rate / sensor.gain, sensor, exposures)
        scenes.append(_Scene(i, rate, mask, truth, floor))
    return scenes


def _bracket(sensor: _Sensor, scene: _Scene, exposures: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    rgb = np.broadcast_to(scene.rate_e, (3, *scene.rate_e.shape))  # every channel: the site's own rate
    return np.stack([sensor.model.expose(rgb, float(t), rng) for t in exposures])


# --- the methods ---------------------------------------------------------------------------------
@dataclass
class _Method:
    name: str
    prepare: Callable  # frames (k, H, W) uint16 -> the method's input (untimed)
    run: Callable  # timed
    to_dn_per_s: Callable  # the output -> (H, W) DN/s above black on the mosaic (untimed)
    input: str
    scale: str
    notes: str
    version: str
    excluded: Callable | None = None  # a part of ``run`` timed apart (HDRutils' demosaic)
    excluded_what: str = ""


@dataclass
class _Ctx:
    sensor: _Sensor
    exposures: np.ndarray
    height: int
    width: int

    def own_channel(self, rgb: np.ndarray) -> np.ndarray:
        from sim_devices.sensor import cfa_channels

        channels = cfa_channels(self.sensor.cfa_pattern, self.height, self.width)
        return np.take_along_axis(rgb, channels[..., None], axis=2)[..., 0]


def _ours(ctx: _Ctx, method: str) -> _Method:
    from processing.hdr.brackets import merge_raw
    from processing.hdr.model import NoiseModel

    s, exposures = ctx.sensor, ctx.exposures
    noise = NoiseModel(s.gain, s.read_dn, source="rig")

    def run(frames):
        return merge_raw(frames, exposures, s.black, s.white, noise, method=method).radiance

    from drivers.contracts.version import __version__

    what = (
        "minimum-variance weights t²/σ² from a Poisson first pass"
        if method == "optimal"
        else "Σ(y − black) / Σt over unsaturated samples"
    )
    return _Method(
        f"mirrorgonio_{method}",
        lambda frames: frames,
        run,
        lambda out: out,
        input="the raw uint16 mosaic (k, H, W) with its black level; saturation measured from the frames",
        scale="exact (DN/s above black)",
        notes=f"processing.hdr.brackets.merge_raw(method={method!r}): {what}; the rig's noise model "
        f"(gain {s.gain:.4g} e-/DN, read noise {s.read_dn:.4g} DN); numba kernel, parallel over rows",
        version=__version__,
    )


def _hdrutils(ctx: _Ctx) -> _Method | str:
    try:
        with warnings.catch_warnings():  # colour-demosaicing imports scipy.ndimage.filters (deprecated)
            warnings.simplefilter("ignore", DeprecationWarning)
            merge_module = importlib.import_module("HDRutils.merge")
            import colour_demosaicing
    except ImportError:
        return PEER_EXTRA
    except Exception as exc:  # noqa: BLE001 - a peer that does not even import is reported, not fatal
        return f"not usable: import failed: {type(exc).__name__}: {exc}"
    from importlib.metadata import version

    s, exposures, k = ctx.sensor, ctx.exposures, len(ctx.exposures)
    names = [f"frame-{i}" for i in range(k)]

    def prepare(frames):
        metadata = {
            "N": k,
            "exp": exposures.astype(np.float64).copy(),
            "gain": np.ones(k),
            "aperture": np.ones(k),
            "h": ctx.height,
            "w": ctx.width,
            "black_level": np.full(4, float(s.black)),
            # What HDRutils' get_metadata sets for a raw file: 0.98 of the reported white level.
            "saturation_point": 0.98 * s.white,
            "color_space": "raw",
            "raw_format": False,
            "libraw_scale": lambda img: img,
        }
        return metadata, dict(zip(names, frames, strict=True))

    def run(prepared):
        metadata, store = prepared
        saved = merge_module.io, merge_module.tqdm
        merge_module.io = types.SimpleNamespace(imread=lambda f, libraw=True, **_: store[f])
        merge_module.tqdm = types.SimpleNamespace(tqdm=lambda it, **_: it)
        try:
            hdr, _ = merge_module.imread_merge_demosaic(names, metadata, False, s.cfa_pattern, "bilinear")
        finally:
            merge_module.io, merge_module.tqdm = saved
        return hdr

    bayer = np.zeros((ctx.height, ctx.width))  # the demosaic's cost does not depend on the values

    def demosaic(_prepared):
        return colour_demosaicing.demosaicing_CFA_Bayer_bilinear(bayer, pattern=s.cfa_pattern) @ np.eye(3)

    return _Method(
        "hdrutils",
        prepare,
        run,
        ctx.own_channel,
        input="the raw uint16 mosaics with their black level (HDRutils subtracts it), exposure times, "
        "gain and aperture 1, saturation point 0.98 x white level (HDRutils' default)",
        scale="exact: its raw-colour-space output is DN/s above black; each photosite's own channel "
        "taken from its bilinear demosaic (which keeps the sampled channel's value)",
        notes="HDRutils.merge.imread_merge_demosaic (what HDRutils.merge(..., demosaic_first=False, "
        "color_space='raw') runs): Σ(y − black)/Σt over samples whose 2x2 Bayer tile is below the "
        "saturation point, the shortest exposure always used. HDRutils has no in-memory API (file "
        "names only): its module's `io` reader and `tqdm` were swapped for the call to serve the "
        "frames from memory. Its time includes the bilinear demosaic it always runs; "
        "time_s_merge_only_est subtracts that demosaic (timed apart) and is what the speed-up uses",
        version=version("HDRutils"),
        excluded=demosaic,
        excluded_what="colour_demosaicing.demosaicing_CFA_Bayer_bilinear + the colour matrix, as inside the call",
    )


def _colour_hdri(ctx: _Ctx) -> _Method | str:
    try:
        from colour_hdri import Image, ImageStack, Metadata, image_stack_to_HDRI
    except ImportError:
        return PEER_EXTRA
    except Exception as exc:  # noqa: BLE001
        return f"not usable: import failed: {type(exc).__name__}: {exc}"
    from importlib.metadata import version

    s, exposures = ctx.sensor, ctx.exposures
    order = np.argsort(exposures)

    def prepare(frames):
        stack = ImageStack()
        for i in order:
            data = (frames[i].astype(np.float64) - s.black) / s.range_dn
            # f/1 at ISO 12.5 with its k = 12.5: average_luminance(N, t, S) = N² k / (t S) = 1 / t.
            stack.append(Image(data=data, metadata=Metadata(f_number=1.0, exposure_time=float(exposures[i]), iso=12.5)))
        return stack

    def run(stack):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "image channels contain negative or equal to zero values"
            return image_stack_to_HDRI(stack)

    return _Method(
        "colour_hdri",
        prepare,
        run,
        lambda out: out * s.range_dn,
        input="single-channel float64 images of the mosaic, (y − black) / (white − black), sorted from the "
        "shortest exposure to the longest, metadata f/1, ISO 12.5, exposure time",
        scale="exact: output x (white − black) is DN/s above black (L = 1/t with that metadata)",
        notes="colour_hdri.image_stack_to_HDRI with its default weighting_function_Debevec1997 and no "
        "camera response (linear data): weights depend on the pixel value only; values clipped to "
        "[eps, 1]; the shortest frame keeps weight 1 above 0.5, the longest below 0.5",
        version=version("colour-hdri"),
    )


def _opencv(ctx: _Ctx, full_range: bool) -> _Method | str:
    try:
        import cv2
    except ImportError:
        return "not installed"
    s, exposures = ctx.sensor, ctx.exposures
    times = exposures.astype(np.float32)
    try:  # OpenCV 4 asserts 8-bit input in MergeDebevec's look-up table; 5 accepts 16-bit.
        cv2.createMergeDebevec().process([np.zeros((2, 2), np.uint16)] * 2, np.array([1.0, 2.0], np.float32))
    except cv2.error as exc:
        return f"rejects 16-bit input: {str(exc).strip().splitlines()[-1]}"
    scale = 65535.0 / s.range_dn if full_range else 1.0

    def prepare(frames):
        signal = np.clip(frames.astype(np.int32) - s.black, 0, None)
        if full_range:
            signal = np.minimum(np.rint(signal * scale), 65535)
        return [f.astype(np.uint16) for f in signal]

    def run(images):
        return cv2.createMergeDebevec().process(images, times)

    if full_range:
        given = (
            "uint16 single-channel images, black removed (negatives clipped to 0) and scaled by "
            f"65535/(white − black) = {scale:.4g} to span the 16-bit range"
        )
        how = (
            "16-bit input goes through a 65536-entry linear response and hat weights peaking at 32767 "
            "(zero at 0 and 65535), averaged in the log domain (a weighted geometric mean, biased low "
            "where the samples are noisy)"
        )
    else:
        given = "uint16 single-channel images, black removed (negatives clipped to 0), 12-bit values unscaled"
        how = (
            "the hat weights span 0..65535, so a 12-bit sample's weight grows up to the clipping level "
            "(4095 is weighted ~1/8 of the peak, far from zero): clipped samples are averaged in"
        )
    return _Method(
        "opencv_debevec" if full_range else "opencv_debevec_12bit",
        prepare,
        run,
        lambda out: out.astype(np.float64) / scale,
        input=given,
        scale=(
            "exact: the linear response makes the output (value / "
            f"t){' / ' + format(scale, '.4g') if full_range else ''} DN/s above black"
        ),
        notes=f"cv2.createMergeDebevec().process(images, times) without a response (linear): {how}; "
        f"float32 output; OpenCV threads: {cv2.getNumThreads()}",
        version=cv2.__version__,
    )


# --- errors against the truth ---------------------------------------------------------------------
@dataclass
class _Errors:
    n: int = 0
    abs_sum: float = 0.0
    sq_sum: float = 0.0
    signed_sum: float = 0.0
    nonfinite: int = 0

    def add(self, estimate: np.ndarray, truth: np.ndarray) -> None:
        rel = estimate.astype(np.float64) / truth - 1.0
        finite = np.isfinite(rel)
        self.nonfinite += int(rel.size - np.count_nonzero(finite))
        rel = rel[finite]
        self.n += rel.size
        self.abs_sum += float(np.abs(rel).sum())
        self.sq_sum += float(np.square(rel).sum())
        self.signed_sum += float(rel.sum())

    def report(self) -> dict:
        if self.n == 0:
            return {"mean_abs_rel_error_pct": None, "rms_rel_error_pct": None, "bias_pct": None}
        return {
            "mean_abs_rel_error_pct": round(100.0 * self.abs_sum / self.n, 4),
            "rms_rel_error_pct": round(100.0 * math.sqrt(self.sq_sum / self.n), 4),
            "bias_pct": round(100.0 * self.signed_sum / self.n, 4),
        }


@dataclass
class _State:
    method: _Method
    times: list[float]
    excluded_times: list[float]
    errors: _Errors = field(default_factory=_Errors)
    first_call_s: float = 0.0
    failed: str | None = None


# --- the benchmark --------------------------------------------------------------------------------
def bench_hdr(
    positions: int = 66,
    exposures: int = 5,
    width: int = 2000,
    height: int = 1312,
    repeat: int = 1,
    seed: int = 0,
    *,
    rig_path=None,
    peers: bool = True,
    distinct_scenes: int = DISTINCT_SCENES,
) -> dict:
    """Merge ``positions`` brackets of ``exposures`` frames with every method; time and error of each.

    ``repeat`` > 1 times every merge that many times per position (the median of the
    per-repeat totals is reported). ``peers=False`` runs this project's merges only.
    """
    t_start = time.perf_counter()
    if positions < 1:
        raise BenchmarkError(f"positions: must be at least 1, got {positions}")
    if not 2 <= exposures <= 16:
        raise BenchmarkError(f"exposures: must be between 2 and 16, got {exposures}")
    for name, value in (("width", width), ("height", height)):
        if value < 4 or value % 2:
            raise BenchmarkError(f"{name}: must be an even number of pixels, at least 4 (a Bayer mosaic), got {value}")
    if repeat < 1:
        raise BenchmarkError(f"repeat: must be at least 1, got {repeat}")

    from drivers.contracts.rig import load_rig
    from sim_devices.sensor import SensorModel

    rig = _rig_at_size(load_rig(rig_path), width, height)
    model = SensorModel.from_rig(rig.camera, noise=True)
    sensor = _Sensor(
        model.cfa_pattern,
        int(model.black_level_dn),
        int(model.white_level_dn),
        model.gain_e_per_dn,
        model.read_noise_e / model.gain_e_per_dn,
        model,
    )
    times_s = exposure_times(exposures)
    ctx = _Ctx(sensor, times_s, height, width)

    t0 = time.perf_counter()
    scenes = _scenes(rig, sensor, times_s, distinct_scenes, seed)
    render_s = time.perf_counter() - t0

    methods: dict[str, _Method | str] = {name: _ours(ctx, name.split("_", 1)[1]) for name in OURS}
    if peers:
        methods["hdrutils"] = _hdrutils(ctx)
        methods["colour_hdri"] = _colour_hdri(ctx)
        methods["opencv_debevec"] = _opencv(ctx, full_range=True)
        methods["opencv_debevec_12bit"] = _opencv(ctx, full_range=False)
    else:
        methods.update({name: "skipped (peers=False)" for name in PEERS})
    states = {name: _State(m, [0.0] * repeat, [0.0] * repeat) for name, m in methods.items() if isinstance(m, _Method)}

    generate_s = 0.0
    for p in range(positions):
        scene = scenes[p % len(scenes)]
        t0 = time.perf_counter()
        frames = _bracket(sensor, scene, times_s, np.random.default_rng([seed, p]))
        generate_s += time.perf_counter() - t0
        for name, state in states.items():
            if state.failed:
                continue
            m = state.method
            try:
                if p == 0:  # warm-up, untimed: numba's JIT, the peers' lazy imports
                    m.run(m.prepare(frames))
                    if m.excluded:
                        m.excluded(None)
                # The first call on a fresh bracket, right after the previous method's work: timed
                # apart. It is often slower (caches, the allocator's state, the kernel's page
                # handling), by an amount that depends on what ran before, not only on the method.
                prepared = m.prepare(frames)
                t0 = time.perf_counter()
                m.run(prepared)
                state.first_call_s += time.perf_counter() - t0
                del prepared
                # Steady state: the method after its own previous call, as in a run of many brackets.
                out = None
                for r in range(repeat):
                    prepared = m.prepare(frames)
                    t0 = time.perf_counter()
                    out = m.run(prepared)
                    state.times[r] += time.perf_counter() - t0
                    if m.excluded:
                        t0 = time.perf_counter()
                        m.excluded(prepared)
                        state.excluded_times[r] += time.perf_counter() - t0
                    del prepared
                state.errors.add(m.to_dn_per_s(out)[scene.mask], scene.truth)
                del out
            except Exception as exc:  # noqa: BLE001 - a peer failing is a result; ours is not
                if name in OURS:
                    raise
                state.failed = (
                    f"failed at position {p}: {type(exc).__name__}: "
                    f"{str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
                )
        del frames

    return _report(
        rig=rig,
        sensor=sensor,
        scenes=scenes,
        times_s=times_s,
        methods=methods,
        states=states,
        positions=positions,
        repeat=repeat,
        seed=seed,
        width=width,
        height=height,
        render_s=render_s,
        generate_s=generate_s,
        wall_s=time.perf_counter() - t_start,
    )


def _report(
    *,
    rig,
    sensor: _Sensor,
    scenes: list[_Scene],
    times_s: np.ndarray,
    methods: dict,
    states: dict,
    positions: int,
    repeat: int,
    seed: int,
    width: int,
    height: int,
    render_s: float,
    generate_s: float,
    wall_s: float,
) -> dict:
    used = [scenes[p % len(scenes)] for p in range(positions)]
    n_set = sum(int(s.mask.sum()) for s in used)
    floor = math.sqrt(sum(s.floor_rel_var_sum for s in used) / n_set) if n_set else None

    out_methods: dict[str, dict] = {}
    for name, m in methods.items():
        if not isinstance(m, _Method):
            out_methods[name] = {
                "status": m,
                "time_s": None,
                "ms_per_position": None,
                "mean_abs_rel_error_pct": None,
                "rms_rel_error_pct": None,
                "bias_pct": None,
                "notes": m,
            }
            continue
        state = states[name]
        if state.failed:
            out_methods[name] = {
                "status": state.failed,
                "time_s": None,
                "ms_per_position": None,
                "mean_abs_rel_error_pct": None,
                "rms_rel_error_pct": None,
                "bias_pct": None,
                "notes": m.notes,
                "version": m.version,
            }
            continue
        total = statistics.median(state.times)
        entry = {
            "status": "ok",
            "time_s": round(total, 4),
            "ms_per_position": round(1000.0 * total / positions, 3),
            **state.errors.report(),
            "pixels_compared": state.errors.n,
            "nonfinite_pixels": state.errors.nonfinite,
            "time_s_all": [round(t, 4) for t in state.times],
            "time_s_first_call": round(state.first_call_s, 4),
            "input": m.input,
            "scale": m.scale,
            "notes": m.notes,
            "version": m.version,
        }
        if m.excluded:
            excluded = statistics.median(state.excluded_times)
            entry["excluded_part_s"] = round(excluded, 4)
            entry["excluded_part"] = m.excluded_what
            entry["time_s_merge_only_est"] = round(max(total - excluded, 0.0), 4)
        out_methods[name] = entry

    ours = out_methods["mirrorgonio_optimal"]
    result: dict = {
        "benchmark": "hdr",
        "width": width,
        "height": height,
        "positions": positions,
        "exposures_per_position": len(times_s),
        "exposures_s": [float(f"{t:.6g}") for t in times_s],
        "repeat": repeat,
        "seed": seed,
        "scene": {
            "description": (
                "the rig's mirrored ball lit by the truth light, rendered at a few schedule positions "
                "(cycled over the benchmark's positions, fresh seeded sensor noise per position), plus a "
                "smooth background: a horizontal log-uniform gradient from 1e2 to 1e7 e-/s in every channel"
            ),
            "truth_light": rig.simulation.truth,
            "rendered_schedule_positions": [s.position for s in scenes],
            "background_e_per_s": list(BACKGROUND_E_PER_S),
            "diffraction": rig.simulation.diffraction,
        },
        "sensor": {
            "cfa_pattern": sensor.cfa_pattern,
            "black_level_dn": sensor.black,
            "white_level_dn": sensor.white,
            "full_well_e": sensor.model.full_well_e,
            "read_noise_e": sensor.model.read_noise_e,
            "gain_e_per_dn": round(sensor.gain, 5),
        },
        "pixel_set": {
            "rule": (
                f"true signal in the shortest exposure + {CLIP_MARGIN_SIGMA:g} sigma below the clipping level, "
                f"and >= {MIN_DN_LONGEST:g} DN above black in the longest; not on the frame's outermost rows "
                "and columns "
                "(HDRutils' bilinear demosaic alters the sampled value there); the same photosites for every method"
            ),
            "pixels_compared": n_set,
            "fraction_of_photosites": round(n_set / (positions * width * height), 4),
            "true_signal_dn_per_s_range": [
                round(float(min(s.truth.min() for s in used if s.truth.size)), 2) if n_set else None,
                round(float(max(s.truth.max() for s in used if s.truth.size)), 1) if n_set else None,
            ],
            "noise_floor_rms_rel_error_pct": round(100.0 * floor, 4) if floor is not None else None,
            "noise_floor": "RMS relative error of the ideal unbiased merge: weights t^2/sigma^2 from the true "
            "signal, over the frames 3 sigma below clipping (photon, read and quantisation noise)",
        },
        "timing": (
            "time.perf_counter around each method's call, per position, summed over the positions; "
            "time_s is the steady state (the method called on the bracket just after an untimed call of "
            "its own on it; the median over repeats), time_s_first_call the call right after the previous "
            "method's work (reported, not used for the speed-ups); preparing a peer's input is not timed; "
            "one untimed call on the first bracket warms numba's JIT and the peers' imports"
        ),
        "error_definition": "relative error (estimate / truth - 1) per photosite, both in DN/s above black; "
        "mean |.|, RMS and mean (bias), in percent",
        "methods": out_methods,
    }
    target_rows = {}
    for peer in PEERS:
        entry = out_methods.get(peer, {})
        peer_time = entry.get("time_s_merge_only_est", entry.get("time_s"))
        if entry.get("status") != "ok" or not ours.get("time_s") or peer_time is None:
            result[f"speedup_vs_{peer}"] = None
            continue
        speedup = peer_time / ours["time_s"]
        result[f"speedup_vs_{peer}"] = round(speedup, 2)
        if "time_s_merge_only_est" in entry:
            result[f"speedup_vs_{peer}_full_call"] = round(entry["time_s"] / ours["time_s"], 2)

        def not_worse(key, entry=entry):
            return ours[key] is not None and entry[key] is not None and ours[key] <= entry[key] * 1.001 + 1e-3

        target_rows[peer] = {
            "speedup": round(speedup, 2),
            "speedup_first_call": round(
                (entry["time_s_first_call"] - entry.get("excluded_part_s", 0.0)) / ours["time_s_first_call"], 2
            ),
            "at_least_3x_faster": speedup >= TARGET_SPEEDUP,
            "error_not_higher": not_worse("mean_abs_rel_error_pct") and not_worse("rms_rel_error_pct"),
        }
    result["target"] = (
        f"mirrorgonio_optimal at least {TARGET_SPEEDUP:g}x faster than every peer, with a mean |relative "
        "error| and an RMS relative error no higher than the peer's"
    )
    result["target_per_peer"] = target_rows
    result["meets_target"] = (
        all(r["at_least_3x_faster"] and r["error_not_higher"] for r in target_rows.values()) if target_rows else None
    )
    result["peers_measured"] = sorted(target_rows)
    result["machine"] = _machine()
    result["render_s"] = round(render_s, 2)
    result["frame_generation_s"] = round(generate_s, 2)
    result["wall_s"] = round(wall_s, 1)
    return result


def _machine() -> dict:
    import numba

    info = {
        "cpu_count": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "numpy": np.__version__,
        "numba": numba.__version__,
    }
    try:
        import cv2

        info["opencv_threads"] = cv2.getNumThreads()
    except ImportError:  # pragma: no cover - OpenCV is a dependency
        pass
    return info

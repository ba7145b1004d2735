"""The HDR merges ``bench hdr`` and ``bench speed`` time: this project's and its peers'.

Each method is a :class:`MergeMethod`: how its input is prepared from the raw frames
(untimed), the timed call, and how its output is converted to DN/s above black on the
mosaic (untimed). A peer that is not installed, or does not work here, is a string saying
why instead.

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
"""

from __future__ import annotations

import importlib
import types
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import version

import numpy as np

from drivers.contracts.version import __version__
from processing.hdr.brackets import merge_raw
from processing.hdr.model import NoiseModel
from sim_devices.sensor import SensorModel, cfa_channels

PEER_EXTRA = "not installed (pip install 'mirrorgonio[bench]')"


#: Significant digits of a reported speed-up: a ratio, whatever the times' scale (a ratio
#: rounded to a fixed number of decimals reads 0.0 when the two times differ a hundredfold).
SPEEDUP_DIGITS = 3
#: Why a peer's merge-only time is not reported: its part timed apart took as long as the
#: whole call (on a busy host the two timings are disturbed independently).
UNRESOLVED_MERGE_ONLY = (
    "not resolved: the part timed apart took as long as the whole call (a busy host); the speed-up uses the whole call"
)


def significant(value: float, digits: int = SPEEDUP_DIGITS) -> float:
    """``value`` rounded to ``digits`` significant digits.

    Examples
    --------
    >>> significant(0.0012345), significant(123.456), significant(0.0)
    (0.00123, 123.0, 0.0)
    """
    return float(f"{value:.{digits}g}")


def merge_only_s(whole_s: float, excluded_s: float) -> float | None:
    """A peer's own merge time: its whole call less the part timed apart, or None when that
    difference is not positive (the two timings disturbed apart, as on a busy host). The
    caller then compares the whole call and says so: a speed-up over the whole call
    includes the peer's excluded part, so it is the larger figure."""
    own = whole_s - excluded_s
    return own if own > 0 else None


@dataclass
class Sensor:
    """The sensor's constants the merges and the error need; its noise in DN."""

    cfa_pattern: str
    black: int
    white: int
    gain: float  # e⁻/DN
    read_dn: float
    model: SensorModel | None  # None where no frames are simulated

    @property
    def range_dn(self) -> float:
        """White level minus black level: the signal's range in DN."""
        return float(self.white - self.black)

    def variance_dn(self, mean_dn):
        """The variance in DN² of a sample of mean ``mean_dn`` above black: photon, read and
        quantisation noise."""
        return np.maximum(mean_dn, 0.0) / self.gain + self.read_dn**2 + 1.0 / 12.0


@dataclass
class MergeMethod:
    """One HDR merge as the benchmarks run it, and what its report says of it."""

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
class MergeContext:
    """What every method is built for: the sensor, the bracket's exposures (s), the frame size."""

    sensor: Sensor
    exposures: np.ndarray
    height: int
    width: int

    def own_channel(self, rgb: np.ndarray) -> np.ndarray:
        """Each photosite's own channel of an (H, W, 3) image: a mosaic again."""
        channels = cfa_channels(self.sensor.cfa_pattern, self.height, self.width)
        return np.take_along_axis(rgb, channels[..., None], axis=2)[..., 0]


def ours_method(ctx: MergeContext, method: str) -> MergeMethod:
    """This project's merge, :func:`processing.hdr.brackets.merge_raw` with ``method`` ("optimal" or
    "poisson") and the rig's noise model."""
    s, exposures = ctx.sensor, ctx.exposures
    noise = NoiseModel(s.gain, s.read_dn, source="rig")

    def run(frames):
        return merge_raw(frames, exposures, s.black, s.white, noise, method=method).radiance

    what = (
        "minimum-variance weights t²/σ² from a Poisson first pass"
        if method == "optimal"
        else "Σ(y − black) / Σt over unsaturated samples"
    )
    return MergeMethod(
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


def hdrutils_method(ctx: MergeContext) -> MergeMethod | str:
    """HDRutils' merge of raw mosaics, its frames served from memory; why not, when it cannot run."""
    try:
        with warnings.catch_warnings():  # colour-demosaicing imports scipy.ndimage.filters (deprecated)
            warnings.simplefilter("ignore", DeprecationWarning)
            merge_module = importlib.import_module("HDRutils.merge")
            import colour_demosaicing  # noqa: PLC0415 - optional: the bench extra
    except ImportError:
        return PEER_EXTRA
    except Exception as exc:  # noqa: BLE001 - a peer that does not even import is reported, not fatal
        return f"not usable: import failed: {type(exc).__name__}: {exc}"
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

    return MergeMethod(
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
        "time_s_merge_only_est subtracts that demosaic (timed apart) and is what the speed-up uses (when the "
        "difference is positive; merge_only says why not otherwise)",
        version=version("HDRutils"),
        excluded=demosaic,
        excluded_what="colour_demosaicing.demosaicing_CFA_Bayer_bilinear + the colour matrix, as inside the call",
    )


def colour_hdri_method(ctx: MergeContext) -> MergeMethod | str:
    """colour-hdri's ``image_stack_to_HDRI`` on the black-subtracted mosaic; why not, when it cannot run."""
    try:
        from colour_hdri import (  # noqa: PLC0415 - optional: the bench extra
            Image,
            ImageStack,
            Metadata,
            image_stack_to_HDRI,
        )
    except ImportError:
        return PEER_EXTRA
    except Exception as exc:  # noqa: BLE001
        return f"not usable: import failed: {type(exc).__name__}: {exc}"
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

    return MergeMethod(
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


def opencv_method(ctx: MergeContext, full_range: bool) -> MergeMethod | str:
    """OpenCV's Debevec merge on 16-bit images, scaled to the full range or not; why not, when
    it cannot run."""
    try:
        import cv2  # noqa: PLC0415 - heavy
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
    return MergeMethod(
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

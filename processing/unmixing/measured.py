"""A point spread the lab measured, as the templates' kernels.

A lab that has imaged a small LED through its own pinhole (docs/lab-guide.md, "A measured
point spread") knows the camera's blur better than any model of the hole: its shape, its
edge, the sensor's bands and the pixels' response are all in the image. The templates then
convolve each source's sharp image with that image instead of a computed pattern.

The pattern depends on the incident wave's curvature ``1/z1`` through the Fresnel number
``a²/λ · (1/z1 + 1/z2)``, so the LED must stand about where the light's virtual image lies
(:func:`virtual_image_distance`); the ball's astigmatism, which a point on the axis cannot
show, moves the pattern by less than 1 % on the reference rig.
"""

from __future__ import annotations

import hashlib
import io
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from drivers.config_files import read_input_bytes

#: How far the measured pixel pitch may differ from the rig camera's (a different sensor).
PITCH_TOLERANCE = 0.01

#: The largest measured image taken (pixels a side): a pinhole's pattern spans tens of pixels.
MAX_SIDE = 1025

#: The border (pixels) whose median is each channel's background.
BORDER = 3


class PointSpreadError(ValueError):
    """A measured point spread that cannot be used (one line naming the file and the field)."""


@dataclass(frozen=True, eq=False)
class MeasuredKernels:
    """Each channel's measured point spread: ``kernels`` (3, m, m), m odd, each the fraction
    of the point's flux a pixel receives, its centroid on the middle pixel (where the chief ray lands); the LED's
    ``distance_m`` in front of the pinhole; the file it came from. Hashed and compared on the
    content (``digest``), so that the per-process template caches hold across tasks."""

    kernels: np.ndarray
    distance_m: float
    source: str
    digest: str

    def __hash__(self) -> int:
        return hash(self.digest)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, MeasuredKernels) and other.digest == self.digest

    def kernel(self, channel: int, reach: int) -> np.ndarray:
        """Channel ``channel``'s kernel on offsets ``-reach..reach``: cropped, or zero beyond
        what was measured. Not renormalised: light beyond ``reach`` lands outside the template,
        as in the frames."""
        half = self.kernels.shape[1] // 2
        out = np.zeros((2 * reach + 1, 2 * reach + 1))
        keep = min(half, reach)
        out[reach - keep : reach + keep + 1, reach - keep : reach + keep + 1] = self.kernels[
            channel, half - keep : half + keep + 1, half - keep : half + keep + 1
        ]
        return out

    def record(self) -> dict[str, object]:
        """The provenance's record of it."""
        return {"measured": self.source, "led_distance_m": self.distance_m, "pixels": int(self.kernels.shape[1])}


def load_measured_point_spread(path: str | Path, pixel_pitch_m: float) -> MeasuredKernels:
    """The point spread in ``path`` (an ``.npz`` with ``psf`` (3, h, w), ``distance_m`` and
    ``pixel_pitch_m``), checked against the camera's ``pixel_pitch_m`` and centred.

    Raises
    ------
    PointSpreadError
        One line naming the file and what is wrong with it.

    Examples
    --------
    >>> import tempfile
    >>> y, x = np.mgrid[-20:21, -20:21]
    >>> spot = np.exp(-((x - 0.3) ** 2 + (y + 0.2) ** 2) / 18.0)
    >>> path = Path(tempfile.mkdtemp()) / "psf.npz"
    >>> np.savez(path, psf=np.stack([spot] * 3), distance_m=0.186, pixel_pitch_m=5.9e-6)
    >>> kernels = load_measured_point_spread(path, 5.9e-6).kernels
    >>> kernels.shape, round(float(kernels[1].sum()), 3)
    ((3, 41, 41), 0.999)
    >>> [round(float(c), 3) for c in ndimage.center_of_mass(kernels[1])]
    [20.0, 20.0]
    """
    path = Path(path)
    # A 1025² float64 image a channel is 25 MB; a compressed or float32 one less.
    raw = read_input_bytes(
        path, "measured point spread", PointSpreadError, field="camera.measured_point_spread.file", limit=64 * 2**20
    )
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as data:
            fields = {name: data[name] for name in ("psf", "distance_m", "pixel_pitch_m") if name in data}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise PointSpreadError(f"{path}: camera.measured_point_spread.file: not a NumPy .npz ({exc})") from None
    missing = [name for name in ("psf", "distance_m", "pixel_pitch_m") if name not in fields]
    if missing:
        raise PointSpreadError(f"{path}: {missing[0]}: missing (the file needs psf, distance_m and pixel_pitch_m)")
    psf = np.asarray(fields["psf"], dtype=float)
    if psf.ndim != 3 or psf.shape[0] != 3 or min(psf.shape[1:]) < 2 * BORDER + 5 or max(psf.shape[1:]) > MAX_SIDE:
        raise PointSpreadError(
            f"{path}: psf: shape {psf.shape}, expected (3, h, w), one image per channel, "
            f"{2 * BORDER + 5} to {MAX_SIDE} pixels a side"
        )
    distance, pitch = (_positive(path, name, fields[name]) for name in ("distance_m", "pixel_pitch_m"))
    if abs(pitch / pixel_pitch_m - 1.0) > PITCH_TOLERANCE:
        raise PointSpreadError(
            f"{path}: pixel_pitch_m: {pitch:.4g} m, but the rig's camera has {pixel_pitch_m:.4g} m pixels "
            "(measure through the same camera)"
        )
    if not np.all(np.isfinite(psf)):
        raise PointSpreadError(f"{path}: psf: holds values that are not finite")
    kernels = np.stack([_centred(path, channel, image) for channel, image in enumerate(psf)])
    kernels.flags.writeable = False
    digest = hashlib.sha256(kernels.tobytes() + np.float64(distance).tobytes()).hexdigest()
    return MeasuredKernels(kernels, distance, str(path), digest)


def _positive(path: Path, name: str, value: np.ndarray) -> float:
    number = float(np.asarray(value, dtype=float).reshape(-1)[0]) if np.asarray(value).size == 1 else float("nan")
    if not (math.isfinite(number) and number > 0):
        raise PointSpreadError(f"{path}: {name}: must be one positive number")
    return number


def _centred(path: Path, channel: int, image: np.ndarray) -> np.ndarray:
    """One channel's image, background (its border's median) taken off, shifted so that its
    centroid lies on the middle pixel of an odd square, and scaled so that the whole pattern,
    its tail beyond the square extrapolated (:func:`total_flux`), has unit flux."""
    border = np.concatenate(
        [image[:BORDER].ravel(), image[-BORDER:].ravel(), image[:, :BORDER].ravel(), image[:, -BORDER:].ravel()]
    )
    signal = image - np.median(border)
    total = float(signal.sum())
    if not total > 0:
        raise PointSpreadError(f"{path}: psf: channel {'RGB'[channel]} holds no light above its border's level")
    side = min(image.shape) - (1 - min(image.shape) % 2)
    centroid = np.array(ndimage.center_of_mass(signal))
    # Pad, so that the shift moves no light across the edges, then cut the odd square about the
    # centroid's pixel and shift the rest of the way in Fourier space (a sub-pixel, flux-keeping
    # interpolation of a smooth pattern).
    pad = side
    padded = np.pad(signal, pad)
    whole = np.round(centroid).astype(int) + pad
    half = side // 2
    cut = padded[whole[0] - half : whole[0] + half + 1, whole[1] - half : whole[1] + half + 1]
    rest = np.round(centroid) - centroid
    shifted = np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(cut), rest)).real
    return shifted / total_flux(shifted)


def total_flux(kernel: np.ndarray) -> float:
    """The flux of a centred point spread, the part beyond its square extrapolated.

    A hard-edged aperture's pattern falls as ``r⁻³`` far out, so the light outside a square of
    half side ``h`` falls as ``k/h``: the sum inside squares of half side ``R/2 … R`` fitted to
    ``T − k/h`` gives the whole ``T``. On the reference pinhole's pattern, 1.5 % lies beyond
    256 px; the fit on a 257 px square finds the whole to 0.2 %, on 513 px to 0.02 %, where the
    square's own sum misses it by 1.9 % and 1 %.

    Examples
    --------
    A pattern with no tail: its whole is what the square holds.

    >>> y, x = np.mgrid[-40:41, -40:41]
    >>> round(total_flux(np.exp(-(x * x + y * y) / 50.0)) / (50.0 * np.pi), 4)
    1.0
    """
    middle = kernel.shape[0] // 2
    half = np.arange(max(2, middle // 2), middle + 1)
    inside = np.array([kernel[middle - h : middle + h + 1, middle - h : middle + h + 1].sum() for h in half])
    design = np.stack([np.ones(half.size), -1.0 / half], axis=1)
    whole, _ = np.linalg.lstsq(design, inside, rcond=None)[0]
    return float(max(whole, inside[-1]))


def virtual_image_distance(camera_to_ball_m: float, light_to_ball_m: float, ball_radius_m: float) -> float:
    """How far in front of the pinhole the ball shows a point of the light on the line through
    the ball's centre: the convex mirror's virtual image (focal length ``R/2``), paraxial.

    Examples
    --------
    The reference rig: the camera 0.2 m from the ball's centre, the light 108 mm, the ball's
    radius 25.4 mm.

    >>> round(virtual_image_distance(0.2, 0.108, 0.0254) * 1e3, 1)
    185.6
    """
    s = light_to_ball_m - ball_radius_m
    behind = 1.0 / (2.0 / ball_radius_m + 1.0 / s)
    return camera_to_ball_m - ball_radius_m + behind

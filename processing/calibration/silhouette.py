"""The ball's outline in a calibration image, with sub-pixel precision.

A first outline (threshold, the largest bright component's contour, ``cv2.fitEllipse``),
then edges placed by flux conservation along profiles normal to it (:func:`flux_edges`;
:mod:`processing.calibration` says why the camera's blur does not bias them).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from processing.calibration.errors import CalibrationError


# --- results ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ellipse:
    """An ellipse in pixel coordinates (col, row): centre, semi-axes and the angle (degrees)
    of the first axis from the +col direction, as OpenCV's ``fitEllipse`` reports it."""

    centre: tuple[float, float]
    semi_axes: tuple[float, float]
    angle_deg: float

    @classmethod
    def from_cv(cls, box: tuple[Sequence[float], Sequence[float], float]) -> Ellipse:
        (cx, cy), (w, h), angle = box
        return cls((float(cx), float(cy)), (float(w) / 2.0, float(h) / 2.0), float(angle))

    def points(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """``count`` points on the ellipse (evenly in its parameter) and outward unit normals."""
        a, b = self.semi_axes
        phi = math.radians(self.angle_deg)
        t = np.linspace(0.0, 2.0 * math.pi, count, endpoint=False)
        ca, sa = math.cos(phi), math.sin(phi)
        x, y = a * np.cos(t), b * np.sin(t)
        pts = np.column_stack([self.centre[0] + ca * x - sa * y, self.centre[1] + sa * x + ca * y])
        nx, ny = np.cos(t) / a, np.sin(t) / b  # gradient of (x/a)² + (y/b)²
        normals = np.column_stack([ca * nx - sa * ny, sa * nx + ca * ny])
        return pts, normals / np.linalg.norm(normals, axis=1, keepdims=True)

    def curvature(self, count: int) -> np.ndarray:
        """Curvature (1/px) at the points of :meth:`points` (same parameterisation)."""
        a, b = self.semi_axes
        t = np.linspace(0.0, 2.0 * math.pi, count, endpoint=False)
        return a * b / (a * a * np.sin(t) ** 2 + b * b * np.cos(t) ** 2) ** 1.5

    def normalised_radius(self, pts: np.ndarray) -> np.ndarray:
        """``sqrt((x/a)² + (y/b)²)`` of points in the ellipse's frame (1 on the ellipse)."""
        a, b = self.semi_axes
        phi = math.radians(self.angle_deg)
        dx, dy = pts[:, 0] - self.centre[0], pts[:, 1] - self.centre[1]
        x = math.cos(phi) * dx + math.sin(phi) * dy
        y = -math.sin(phi) * dx + math.cos(phi) * dy
        return np.sqrt((x / a) ** 2 + (y / b) ** 2)


@dataclass
class Silhouette:
    """The ball's outline in a calibration image.

    Attributes
    ----------
    points : (N, 2)
        Sub-pixel edge points, pixel coordinates (col, row) with pixel centres at integers.
    normals : (N, 2)
        Outward unit normals of the outline at the points.
    ellipse : Ellipse
        The ellipse fitted to the points (its centre is not the ball centre's projection).
    method : str
        ``"ellipse"`` (flux-balanced edges along normal profiles) or ``"contour"``
        (OpenCV's pixel contour).
    window_px : (x1, x2)
        The profile estimator's windows: levels fitted between x1 and x2 px either side of
        the edge, flux balanced over ±x1 (0, 0 for ``"contour"``).
    blur_px : float
        The edge's 10-90 % width measured from the image.
    levels : (background, interior)
        Median levels outside and inside the outline.
    rejected : int
        Profiles left out (interior features, the image border, outliers).
    image_shape : (H, W)
    curvature : (N,)
        The outline's curvature at the points (1/px), for the estimator's area element.
    line_spread : (offsets, weights)
        The camera's line spread across the edge, measured: the symmetric part of the
        derivative of the median edge profile (out to the windows' far end).
    """

    points: np.ndarray
    normals: np.ndarray
    ellipse: Ellipse
    method: str
    window_px: tuple[float, float]
    blur_px: float
    levels: tuple[float, float]
    rejected: int
    image_shape: tuple[int, int]
    curvature: np.ndarray | None = None  # (N,) of the outline at the points, 1/px
    line_spread: tuple[np.ndarray, np.ndarray] | None = None  # (offsets px, weights summing to 1)


# --- images ------------------------------------------------------------------------------------
def mosaic_luminance(mosaic: np.ndarray, black_level: ArrayLike = 0.0) -> np.ndarray:
    """A smooth luminance image from a Bayer mosaic, black level removed.

    The 3x3 binomial filter ``[1 2 1]ᵀ[1 2 1] / 16`` weighs R, G and B as 1:2:1 at every
    site of any 2x2 Bayer tile and is centred, so the result has no checkerboard and no
    half-pixel shift (and conserves light: edges stay where they are).
    """
    m = np.asarray(mosaic, dtype=np.float64)
    if m.ndim != 2:
        raise CalibrationError(f"a mosaic has two dimensions, got shape {m.shape}")
    black = np.asarray(black_level, dtype=np.float64)
    if black.shape == (2, 2):
        black = np.tile(black, ((m.shape[0] + 1) // 2, (m.shape[1] + 1) // 2))[: m.shape[0], : m.shape[1]]
    kernel = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0]) / 16.0
    return cv2.filter2D(m - black, cv2.CV_64F, kernel, borderType=cv2.BORDER_REFLECT_101)


def _as_gray(image: ArrayLike) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3:
        if a.shape[-1] in (3, 4):
            a = a[..., :3].astype(np.float64).mean(axis=-1)
        elif a.shape[0] == 3:
            a = a.astype(np.float64).mean(axis=0)
    if a.ndim != 2:
        raise CalibrationError(f"a calibration image is 2-D (or H x W x 3), got shape {np.shape(image)}")
    if min(a.shape) < 16:
        raise CalibrationError(f"the calibration image is too small ({a.shape[1]} x {a.shape[0]} px)")
    a = a.astype(np.float64)
    finite = np.isfinite(a)
    if finite.mean() < 0.5:
        raise CalibrationError("the calibration image is mostly NaN or infinite")
    if not finite.all():
        a = np.where(finite, a, np.median(a[finite]))
    return a


def _noise_sigma(image: np.ndarray, mask: np.ndarray) -> float:
    """Robust per-pixel noise in ``mask`` from horizontal neighbour differences."""
    diff = np.diff(image, axis=1)[mask[:, 1:] & mask[:, :-1]]
    if diff.size < 10:
        return 0.0
    return float(1.4826 * np.median(np.abs(diff - np.median(diff))) / math.sqrt(2.0))


# --- the silhouette -----------------------------------------------------------------------------
def _coarse_outline(img: np.ndarray) -> tuple[Ellipse, np.ndarray, tuple[float, float]]:
    """Threshold, the largest bright component, its outer contour and ellipse."""
    h, w = img.shape
    lo, hi = np.percentile(img, [1.0, 99.5])
    if not hi - lo > 1e-9 * max(1.0, abs(hi)):
        raise CalibrationError("no ball in the calibration image: it is blank (uniform)")
    smooth = cv2.GaussianBlur(img, (0, 0), 1.5)
    scaled = (np.clip((smooth - lo) / (hi - lo), 0.0, 1.0) * 255.0).astype(np.uint8)
    _, mask = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count < 2:
        raise CalibrationError("no ball in the calibration image: nothing stands out from the background")
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    blob = (labels == largest).astype(np.uint8)
    contours, _ = cv2.findContours(blob, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64)
    filled = np.zeros_like(blob)
    cv2.drawContours(filled, [contour.astype(np.int32)[:, None, :]], -1, 1, thickness=cv2.FILLED)
    inside, outside = filled.astype(bool), ~cv2.dilate(filled, np.ones((5, 5), np.uint8)).astype(bool)
    if inside.sum() < 50 or len(contour) < 20 or outside.sum() < 50:
        raise CalibrationError("no ball in the calibration image: no bright disc-like region")
    level_in, level_out = float(np.median(img[inside])), float(np.median(img[outside]))
    sigma = max(_noise_sigma(img, outside), _noise_sigma(img, inside) * 0.1, 1e-12 * abs(level_in))
    if level_in - level_out < 10.0 * sigma:
        raise CalibrationError(
            f"no ball in the calibration image: the brightest region stands out by only "
            f"{(level_in - level_out) / max(sigma, 1e-300):.1f} noise sigma"
        )
    on_border = (contour[:, 0] <= 1) | (contour[:, 1] <= 1) | (contour[:, 0] >= w - 2) | (contour[:, 1] >= h - 2)
    if on_border.mean() > 0.25:
        raise CalibrationError(
            f"the ball is cut off by the image border ({100 * on_border.mean():.0f} % of its outline)"
        )
    free = contour[~on_border]
    if len(free) < 20:
        raise CalibrationError("no ball in the calibration image: no bright disc-like region")
    ellipse = Ellipse.from_cv(cv2.fitEllipse(free.astype(np.float32)))
    a, b = ellipse.semi_axes
    if not (min(a, b) >= 4.0 and min(a, b) / max(a, b) > 0.5):
        raise CalibrationError(
            f"no ball in the calibration image: the bright region is not disc-like (axes {2 * a:.0f} x {2 * b:.0f} px)"
        )
    rho = ellipse.normalised_radius(free)
    spread = float(np.median(np.abs(rho - 1.0)))
    area_ratio = float(inside.sum()) / (math.pi * a * b)
    if spread > 0.02 + 1.5 / min(a, b) or abs(area_ratio - 1.0) > 0.1:
        raise CalibrationError(
            f"no ball in the calibration image: the bright region is not an ellipse "
            f"(outline {100 * spread:.1f} % off its best ellipse)"
        )
    return ellipse, free, (level_out, level_in)


def _sample(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples at pixel coordinates (..., 2) = (col, row)."""
    coords = np.stack([pts[..., 1].ravel(), pts[..., 0].ravel()])
    return ndimage.map_coordinates(img, coords, order=1, mode="nearest").reshape(pts.shape[:-1])


def _profile_grid(x1: float, x2: float, step: float) -> np.ndarray:
    n = int(math.ceil(x2 / step))
    return np.arange(-n, n + 1) * step


def _line_fit(t: np.ndarray, values: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares line ``a + b t`` per row over the masked samples; also the RMS residual."""
    w = mask.astype(np.float64)
    n = w.sum(axis=1)
    st, sv = (w * t).sum(axis=1), (w * values).sum(axis=1)
    stt, stv = (w * t * t).sum(axis=1), (w * t * values).sum(axis=1)
    den = n * stt - st * st
    b = (n * stv - st * sv) / den
    a = (sv - b * st) / n
    res = (values - (a[:, None] + b[:, None] * t)) * w
    rms = np.sqrt((res**2).sum(axis=1) / np.maximum(n - 2, 1))
    return a, b, rms


def flux_edges(
    profile_at: Callable[[np.ndarray], np.ndarray],
    count: int,
    x1: float,
    x2: float,
    step: float,
    curvature: ArrayLike = 0.0,
    iterations: int = 4,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Flux-balanced edge offsets along ``count`` profiles.

    With lines ``a_i + b_i t`` fitted over [-x2, -x1] (inside) and ``a_o + b_o t`` over
    [x1, x2] (outside) about the current edge, the edge e balances the light over the window:
    ``∫_{-x1}^{x1} O w = ∫_{-x1}^{e} (a_i + b_i t) w + ∫_{e}^{x1} (a_o + b_o t) w``, with
    ``w = 1 + t · curvature`` the area element of a curved outline (blur conserves light in
    the image plane, not along a line: without it a disc's edge comes out ``σ² / 2r`` too far
    in). The windows are then re-centred on the edge and the balance repeated.

    Parameters
    ----------
    profile_at : callable
        ``profile_at(offsets)`` returns the profiles' values at signed distances ``offsets``
        (count, K) along the outward normals.
    count : int
        Number of profiles.
    x1, x2 : float
        The windows, px: lines fitted between x1 and x2 either side of the edge, the light
        balanced over ±x1 (x1 rounded down to the sampling grid).
    step : float
        Sampling step along the profiles, px.
    curvature : float or (count,)
        The outline's curvature at the profiles, 1/px.
    iterations : int
        Re-centrings at most (fewer once the edge moves less than 1e-4 px).

    Returns
    -------
    offsets, inner, outer, rms : (count,)
        The offsets, inner and outer levels at the edge, the inner fit's RMS.
    """
    x1 = step * math.floor(x1 / step + 1e-9)  # the balance runs between grid points
    t = _profile_grid(x1, x2, step)
    inner, outer = (t <= -x1 + 1e-9) & (t >= -x2), (t >= x1 - 1e-9) & (t <= x2)
    middle = np.abs(t) <= x1 + 1e-9
    tm = t[middle]
    trap = np.full(tm.size, step)
    trap[0] = trap[-1] = step / 2.0
    kappa = np.broadcast_to(np.asarray(curvature, dtype=float), (count,))
    weights = 1.0 + kappa[:, None] * tm[None, :]

    def primitive(a: np.ndarray, b: np.ndarray, x: float | np.ndarray) -> np.ndarray:  # ∫ (a + b t)(1 + κ t) dt
        return a * x + (b + a * kappa) * x * x / 2.0 + b * kappa * x**3 / 3.0

    s0 = np.zeros(count)
    shape = (count, t.size)
    for _ in range(iterations):
        values = profile_at(s0[:, None] + t[None, :])
        a_i, b_i, rms_i = _line_fit(np.broadcast_to(t, shape), values, np.broadcast_to(inner, shape))
        a_o, b_o, _ = _line_fit(np.broadcast_to(t, shape), values, np.broadcast_to(outer, shape))
        area = np.sum(values[:, middle] * weights * trap[None, :], axis=1)
        fixed = primitive(a_o, b_o, x1) - primitive(a_i, b_i, -x1) - area
        e = np.zeros(count)
        for _ in range(8):  # Newton on a cubic that is nearly linear
            g = primitive(a_i, b_i, e) - primitive(a_o, b_o, e) + fixed
            slope = ((a_i - a_o) + (b_i - b_o) * e) * (1.0 + kappa * e)
            with np.errstate(divide="ignore", invalid="ignore"):
                e = np.clip(np.nan_to_num(e - g / slope), -x1, x1)
        s0 = s0 + e
        if np.max(np.abs(e)) < 1e-4:
            break
    return s0, a_i, a_o, rms_i


def _edge_windows(img: np.ndarray, ellipse: Ellipse, count: int, step: float) -> tuple[float, float, float]:
    """The edge's blur, the 10-90 % width of the median profile across the outline over a long reach, and the
    estimator's windows ``x1, x2`` (px, on the sampling grid) that it sets."""
    small = min(ellipse.semi_axes)
    reach = min(0.45 * small, 120.0)
    pts, normals = ellipse.points(count)
    t = np.arange(-reach, reach + step / 2, step)
    long = _sample(img, pts[:, None, :] + t[None, :, None] * normals[:, None, :])
    median = np.median(long, axis=0)
    lo_lvl, hi_lvl = np.median(median[t > 0.8 * reach]), np.median(median[t < -0.8 * reach])
    frac = (median - lo_lvl) / max(hi_lvl - lo_lvl, 1e-300)
    inside_t = t[frac >= 0.9]
    outside_t = t[frac <= 0.1]
    t90 = inside_t[inside_t < 0].max() if np.any(inside_t < 0) else 0.0
    t10 = outside_t[outside_t > t90].min() if np.any(outside_t > t90) else 0.0
    blur = float(max(t10 - t90, 1.0))
    x1 = step * math.floor((1.25 * blur + 2.0) / step)
    x2 = x1 + step * math.ceil(max(4.0, blur) / step)
    if x2 > 0.6 * small:
        raise CalibrationError(
            f"the ball's image is too small for its blur (radius {small:.0f} px, edge {blur:.0f} px wide)"
        )
    return blur, x1, x2


def _edge_profiles(
    img: np.ndarray, ellipse: Ellipse, count: int, windows: tuple[float, float], step: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Flux-balanced edges along ``count`` profiles normal to ``ellipse``, those whose windows stay in the
    image: the profiles' points, normals and curvature, and what :func:`flux_edges` returns for them."""
    h, w = img.shape
    x1, x2 = windows
    pts, normals = ellipse.points(count)
    far = pts[:, None, :] + (x2 + 0.5 * x1) * np.array([-1.0, 1.0])[None, :, None] * normals[:, None, :]
    inside_image = np.all(
        (far[..., 0] >= 1) & (far[..., 0] <= w - 2) & (far[..., 1] >= 1) & (far[..., 1] <= h - 2), axis=1
    )
    pts, normals = pts[inside_image], normals[inside_image]
    curvature = ellipse.curvature(count)[inside_image]

    def profile_at(offsets: np.ndarray) -> np.ndarray:
        return _sample(img, pts[:, None, :] + offsets[..., None] * normals[:, None, :])

    return pts, normals, curvature, flux_edges(profile_at, len(pts), x1, x2, step, curvature)


def _usable_edges(
    edge: np.ndarray, offset: np.ndarray, contrast: np.ndarray, rms: np.ndarray, x1: float, count: int
) -> np.ndarray:
    """The edge points to keep: the typical contrast, a clean inner level, an edge near the outline it was
    sought from, and no outlier from the ellipse fitted to those."""
    typical = np.median(contrast)
    noise = np.median(rms)
    good = (
        (contrast > 0.7 * typical)
        & (contrast < 1.3 * typical)
        & (rms < 3.0 * noise + 0.01 * abs(typical))
        & (np.abs(offset) < 0.5 * x1)
    )
    if good.sum() < max(20, 0.25 * count):
        raise CalibrationError(f"the ball's outline is not clear enough: {good.sum()} of {count} edge profiles usable")
    fitted = Ellipse.from_cv(cv2.fitEllipse(edge[good].astype(np.float32)))
    dev = (fitted.normalised_radius(edge) - 1.0) * min(fitted.semi_axes)
    mad = 1.4826 * np.median(np.abs(dev[good] - np.median(dev[good])))
    return good & (np.abs(dev) < max(5.0 * mad, 0.25))


def _line_spread(
    img: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    levels: tuple[np.ndarray, np.ndarray],
    x2: float,
    step: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The camera's line spread across the edge, ``(offsets, weights)``: the derivative of the median edge
    profile normalised by each point's ``levels = (outside, inside)``, symmetrised (the camera's blur is
    symmetric; the Fresnel rim adds an odd part)."""
    a_out, a_in = levels
    m = int(math.ceil(x2 / step))
    t = np.arange(-m, m + 1) * step
    long = _sample(img, points[:, None, :] + t[None, :, None] * normals[:, None, :])
    esf = np.median((long - a_out[:, None]) / (a_in - a_out)[:, None], axis=0)
    lsf = -np.gradient(esf, step)
    lsf = np.clip(0.5 * (lsf + lsf[::-1]), 0.0, None)
    lsf = lsf / lsf.sum() if lsf.sum() > 0 else np.eye(1, t.size, m)[0]
    return t, lsf


def detect_silhouette(image: ArrayLike, *, method: str = "ellipse", profiles: int | None = None) -> Silhouette:
    """Find the mirrored ball's outline in a calibration image, with sub-pixel precision.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        Linear intensities with the black level removed (a raw mosaic through
        :func:`mosaic_luminance`, or a merged HDR image). The ball, lit by its
        surroundings, must be the largest bright disc-like region and lie mostly inside
        the image.
    method : ``"ellipse"`` or ``"contour"``
        ``"ellipse"``: flux-balanced edges along profiles normal to a first ellipse (the
        precise one; see the module's notes). ``"contour"``: OpenCV's pixel contour of the
        thresholded disc, for a quick look.
    profiles : int, optional
        Number of normal profiles (default: about one per pixel of the outline).

    Note: under perspective the fitted ellipse's centre is **not** the projection of the
    ball's centre; use :func:`solve_ball_centre` for the centre.

    Raises
    ------
    CalibrationError
        A blank image, no disc-like bright region, or a ball cut off by the border.
    """
    if method not in ("ellipse", "contour"):
        raise CalibrationError(f"unknown silhouette method {method!r} (ellipse, contour)")
    img = _as_gray(image)
    h, w = img.shape
    ellipse, contour, (level_out, level_in) = _coarse_outline(img)
    if method == "contour":
        rho_pts = contour - np.asarray(ellipse.centre)
        normals = rho_pts / np.linalg.norm(rho_pts, axis=1, keepdims=True)
        return Silhouette(
            contour, normals, ellipse, "contour", (0.0, 0.0), float("nan"), (level_out, level_in), 0, (h, w)
        )

    a, b = ellipse.semi_axes
    perimeter = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))
    count = profiles or int(np.clip(round(perimeter), 64, 4096))
    step = 0.25
    blur, x1, x2 = _edge_windows(img, ellipse, count, step)
    for _ in range(2):  # the second pass along the normals of the ellipse fitted to the first pass's edges
        pts, normals, curvature, (offset, a_in, a_out, rms) = _edge_profiles(img, ellipse, count, (x1, x2), step)
        edge = pts + offset[:, None] * normals
        good = _usable_edges(edge, offset, a_in - a_out, rms, x1, count)
        ellipse = Ellipse.from_cv(cv2.fitEllipse(edge[good].astype(np.float32)))
    rejected = count - int(good.sum())
    points, normals, a_in, a_out = edge[good], normals[good], a_in[good], a_out[good]
    levels = (float(np.median(a_out)), float(np.median(a_in)))
    line_spread = _line_spread(img, points, normals, (a_out, a_in), x2, step)
    return Silhouette(
        points, normals, ellipse, "ellipse", (x1, x2), blur, levels, rejected, (h, w), curvature[good], line_spread
    )

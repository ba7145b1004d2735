"""Measured geometry: where the mirrored ball really is, from a calibration image.

The reference work found that the relative position of camera, ball and light must be
known precisely; this module measures the ball's position, so that the processing need not
trust the rig description's.

A *calibration image* shows the ball lit by its surroundings: a bright disc-like region
(the room reflected in the mirror) against a darker background. Its outline is the
silhouette of the sphere: the cone of rays from the camera's centre of projection that
graze the ball. From the outline and the ball's known radius R the centre C follows,
because every silhouette ray is tangent to the sphere: for each edge point's unit ray d_i
(back-projected through the camera matrix), the distance from C to the ray is R,
``|C - (C·d_i) d_i| = R``.

Under perspective the silhouette is an ellipse (the cone cut by the image plane) whose
centre is **not** the projection of the ball's centre: for a ball whose centre lies at an
angle γ from the optical axis and subtends a half-angle β, the ellipse's major axis runs
from ``f tan(γ - β)`` to ``f tan(γ + β)`` from the principal point, so its centre lies
``f [(tan(γ + β) + tan(γ - β)) / 2 - tan γ]`` farther out than the centre's projection
``f tan γ`` (several pixels for a ball 10-15° off the axis). :func:`solve_ball_centre`
therefore fits the tangent cone, not the ellipse's centre.

The edge. Along profiles normal to a first outline (OpenCV contour + ``cv2.fitEllipse``),
the edge is placed by flux conservation: where a sharp step between the straight lines
fitted to the profile inside and outside would hold the same light as the measured
profile over a window symmetric about the edge. The camera's blur (the aperture's disc,
the Airy pattern and its slow tails, the pixel) conserves light and is symmetric, so the
estimate is unbiased by it. What it does see is the ball's own reflectance: a metal's
Fresnel reflectance rises to 1 at grazing incidence, so the outermost sliver of the
disc is brighter than the interior's trend, and the flux-balanced edge lands outside the
true tangent — about half a pixel for chrome at the defaults' resolution reduced to
23.6 µm pixels, 0.8 mm in the ball's distance. Given the ball's complex refractive index,
:func:`solve_ball_centre` predicts that shift for each edge point (the same estimator
applied to the Fresnel profile of a sharp silhouette, at the fitted geometry) and
removes it.

The uncertainty reported is statistical (the scatter of the edge points about the fitted
cone, through the fit's Jacobian). Systematic errors are not in it: the intrinsics, and
the radius (the solution scales with R: a 10 µm error in R moves the centre by
10 µm × |C| / R, 80 µm at 20 cm).

:func:`angle_sensitivity` says what an error in the ball's position costs: how far the
recovered outgoing angles move when the ball is 1 mm from where the processing thinks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from drivers.contracts.rig import Rig
from drivers.pose import Pose
from processing.trace import RigGeometry, ball_pixel_grid, trace_pixels


class CalibrationError(ValueError):
    """A calibration image or fit that cannot give the ball's position (one line)."""


# --- results ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ellipse:
    """An ellipse in pixel coordinates (col, row): centre, semi-axes and the angle (degrees)
    of the first axis from the +col direction, as OpenCV's ``fitEllipse`` reports it."""

    centre: tuple[float, float]
    semi_axes: tuple[float, float]
    angle_deg: float

    @classmethod
    def from_cv(cls, box) -> Ellipse:
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


@dataclass
class BallFit:
    """The ball's centre measured from its silhouette.

    Attributes
    ----------
    centre_camera : (3,)
        Centre in camera coordinates (OpenCV: x right, y down, z forward), metres.
    sigma_camera : (3,)
        1-sigma statistical uncertainty per camera axis, metres.
    covariance_camera : (3, 3)
    residuals : (N,)
        Distance from the centre to each (corrected) silhouette ray minus R, metres.
    centre_rig, sigma_rig : (3,) or None
        The same in the rig frame, when the camera's extrinsics were given.
    naive_centre_camera : (3,)
        For comparison: the ellipse centre back-projected, at the distance its apparent
        size gives (what ignoring perspective would report).
    rim_shift_px : float
        Median inward shift applied to the edge points for the Fresnel rim (0 without
        the ball's refractive index).
    points_used : int
    """

    centre_camera: np.ndarray
    sigma_camera: np.ndarray
    covariance_camera: np.ndarray
    residuals: np.ndarray
    radius_m: float
    centre_rig: np.ndarray | None = None
    sigma_rig: np.ndarray | None = None
    naive_centre_camera: np.ndarray | None = None
    rim_shift_px: float = 0.0
    points_used: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def rms_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))


# --- images ------------------------------------------------------------------------------------
def mosaic_luminance(mosaic: np.ndarray, black_level=0.0) -> np.ndarray:
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


def _as_gray(image) -> np.ndarray:
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
def _coarse_outline(img: np.ndarray):
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


def _line_fit(t, values, mask):
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


def _flux_edges(profile_at, count: int, x1: float, x2: float, step: float, curvature=0.0, iterations: int = 4):
    """Flux-balanced edge offsets along ``count`` profiles.

    ``profile_at(offsets)`` returns the profiles' values at signed distances ``offsets``
    (count, K) along the outward normals. With lines ``a_i + b_i t`` fitted over
    [-x2, -x1] (inside) and ``a_o + b_o t`` over [x1, x2] (outside) about the current
    edge, the edge e balances the light over the window:
    ``∫_{-x1}^{x1} O w = ∫_{-x1}^{e} (a_i + b_i t) w + ∫_{e}^{x1} (a_o + b_o t) w``, with
    ``w = 1 + t · curvature`` the area element of a curved outline (blur conserves light in
    the image plane, not along a line: without it a disc's edge comes out ``σ² / 2r`` too far
    in). The windows are then re-centred on the edge and the balance repeated.

    Returns the offsets (count,), inner and outer levels at the edge, the inner fit's RMS.
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

    def primitive(a, b, x):  # ∫ (a + b t)(1 + κ t) dt
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


def _edge_profiles(img: np.ndarray, ellipse: Ellipse, count: int, windows: tuple[float, float], step: float):
    """Flux-balanced edges along ``count`` profiles normal to ``ellipse``, those whose windows stay in the
    image: the profiles' points, normals and curvature, and what :func:`_flux_edges` returns for them."""
    h, w = img.shape
    x1, x2 = windows
    pts, normals = ellipse.points(count)
    far = pts[:, None, :] + (x2 + 0.5 * x1) * np.array([-1.0, 1.0])[None, :, None] * normals[:, None, :]
    inside_image = np.all(
        (far[..., 0] >= 1) & (far[..., 0] <= w - 2) & (far[..., 1] >= 1) & (far[..., 1] <= h - 2), axis=1
    )
    pts, normals = pts[inside_image], normals[inside_image]
    curvature = ellipse.curvature(count)[inside_image]

    def profile_at(offsets):
        return _sample(img, pts[:, None, :] + offsets[..., None] * normals[:, None, :])

    return pts, normals, curvature, _flux_edges(profile_at, len(pts), x1, x2, step, curvature)


def _usable_edges(edge, offset, contrast, rms, x1: float, count: int) -> np.ndarray:
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


def _line_spread(img, points, normals, levels, x2: float, step: float) -> tuple[np.ndarray, np.ndarray]:
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


def detect_silhouette(image, *, method: str = "ellipse", profiles: int | None = None) -> Silhouette:
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


# --- the centre -----------------------------------------------------------------------------------
def _rays(k_inv: np.ndarray, pts: np.ndarray) -> np.ndarray:
    homogeneous = np.column_stack([pts, np.ones(len(pts))])
    d = homogeneous @ k_inv.T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _cone_guess(d: np.ndarray, radius: float) -> np.ndarray:
    """Closed form: tangent rays satisfy ``d_i · a = cos β``, i.e. ``d_i · w = 1``."""
    w, *_ = np.linalg.lstsq(d, np.ones(len(d)), rcond=None)
    norm = float(np.linalg.norm(w))
    if not norm > 1.0:
        raise CalibrationError("the silhouette rays do not form a cone around a ball")
    sin_beta = math.sqrt(1.0 - 1.0 / norm**2)
    return (w / norm) * radius / sin_beta


def _mean_reflectance(ball_index, cos_i: np.ndarray) -> np.ndarray:
    n, k = (np.atleast_1d(np.asarray(x, dtype=float)) for x in ball_index)
    eta = (n + 1j * k)[None, :]
    c = np.clip(cos_i, 0.0, 1.0)[:, None]
    root = np.sqrt(eta * eta - (1.0 - c * c))
    r_s = (c - root) / (c + root)
    r_p = (eta * eta * c - root) / (eta * eta * c + root)
    return (0.5 * (np.abs(r_s) ** 2 + np.abs(r_p) ** 2)).mean(axis=1)


def fresnel_rim_shift_px(
    kappa,
    sin_beta: float,
    ball_index,
    window_px: tuple[float, float],
    curvature: float = 0.0,
    line_spread=None,
    step: float = 0.05,
) -> np.ndarray:
    """Outward shift (px) of the flux-balanced edge caused by the Fresnel rim.

    For a sharp silhouette, the profile a pixel ``δ`` inside the edge sees is the ball's
    reflectance ``F(α)`` at the incidence of the ray ``ψ = κ δ`` inside the tangent
    (``κ``: radians per pixel along the normal), where the ray's impact parameter
    ``|C| sin(β - ψ) = R sin α``, blurred by the measured ``line_spread`` (offsets, weights);
    the estimator of :func:`detect_silhouette` applied to that profile gives the shift.
    (The blur matters: it carries the Fresnel curve's dip at 70-80° into the inner window.)
    The smooth parts of the interior (the room, ``cos⁴``) are absorbed by the estimator's
    fitted lines and do not enter.
    """
    kappa = np.atleast_1d(np.asarray(kappa, dtype=float))
    x1, x2 = window_px
    beta = math.asin(sin_beta)
    if line_spread is not None:
        lsf_t, lsf_w = (np.asarray(x, dtype=float) for x in line_spread)
        half = int(math.ceil(np.max(np.abs(lsf_t)) / step))
        kernel = np.interp(np.arange(-half, half + 1) * step, lsf_t, lsf_w, left=0.0, right=0.0)
        kernel = kernel / kernel.sum()
    else:
        half, kernel = 0, np.ones(1)
    reach = x1 + x2 + 2.0 + half * step
    grid = np.arange(-int(math.ceil(reach / step)), int(math.ceil(reach / step)) + 1) * step

    # Cell averages over 16 sub-samples: F rises as sqrt(distance) into the edge.
    sub = grid[:, None] + (np.arange(16) + 0.5 - 8.0)[None, :] * (step / 16.0)
    delta = np.maximum(-sub, 0.0)  # px inside the edge
    psi = kappa[:, None, None] * delta[None, :, :]
    sin_alpha = np.clip(np.sin(np.clip(beta - psi, -math.pi / 2, math.pi / 2)) / sin_beta, -1.0, 1.0)
    cos_alpha = np.sqrt(1.0 - sin_alpha**2)
    reflectance = _mean_reflectance(ball_index, cos_alpha.ravel()).reshape(cos_alpha.shape)
    sharp = np.where(sub[None, :, :] < 0.0, reflectance, 0.0).mean(axis=2)
    blurred = np.stack([np.convolve(row, kernel, mode="same") for row in sharp])

    def profile_at(offsets):
        return np.stack([np.interp(o, grid, b) for o, b in zip(offsets, blurred, strict=True)])

    shift, *_ = _flux_edges(profile_at, kappa.size, x1, x2, step, curvature, iterations=6)
    return shift


def _tangent_fit(d: np.ndarray, start: np.ndarray, radius: float):
    """Least squares (Levenberg-Marquardt) of the distances from the centre to the rays ``d`` minus R."""

    def residual(c):
        q = c[None, :] - (d @ c)[:, None] * d
        return np.linalg.norm(q, axis=1) - radius

    def jacobian(c):
        q = c[None, :] - (d @ c)[:, None] * d
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    return least_squares(residual, start, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)


def _rim_shift(silhouette: Silhouette, k_inv: np.ndarray, sin_beta: float, ball_index) -> np.ndarray:
    """The Fresnel rim's outward shift (px) at each edge point of a ball of angular radius ``asin(sin_beta)``:
    :func:`fresnel_rim_shift_px` on a grid of the points' radians per pixel along the normal, interpolated."""
    pts = np.asarray(silhouette.points, dtype=float)
    inward = _rays(k_inv, pts - np.asarray(silhouette.normals, dtype=float))
    kappa = np.arccos(np.clip(np.sum(_rays(k_inv, pts) * inward, axis=1), -1.0, 1.0))
    grid = np.linspace(kappa.min(), kappa.max(), 9) if np.ptp(kappa) > 0 else kappa[:1]
    # A straight edge blurred in 1-D, so no curvature weighting: the detection's
    # weighting undoes the 2-D blur of the curved outline, which the model lacks.
    per_grid = fresnel_rim_shift_px(grid, sin_beta, ball_index, silhouette.window_px, 0.0, silhouette.line_spread)
    return np.interp(kappa, grid, per_grid) if grid.size > 1 else np.full(len(pts), per_grid[0])


def solve_ball_centre(
    silhouette: Silhouette,
    camera_matrix,
    radius_m: float,
    *,
    extrinsics: tuple[np.ndarray, np.ndarray] | None = None,
    ball_index: tuple | None = None,
    iterations: int = 3,
) -> BallFit:
    """The ball's centre from its silhouette and known radius.

    Every silhouette ray is tangent to the sphere: for each edge point's back-projected
    unit ray d_i the distance from the centre C to the ray, ``|C - (C·d_i) d_i|``, equals
    R. Solved by ``scipy.optimize.least_squares`` from the closed-form cone fit
    (``d_i · w = 1``, the cone's axis ``w / |w|`` and half-angle ``arccos(1 / |w|)``).

    Parameters
    ----------
    silhouette : Silhouette
    camera_matrix : (3, 3)
        OpenCV intrinsics K (no lens distortion).
    radius_m : float
        The ball's radius.
    extrinsics : (R, t), optional
        ``x_cam = R X + t``: also report the centre in the rig frame.
    ball_index : (n, k), optional
        The ball's complex refractive index (per channel; the reflectances are averaged):
        corrects the edge points for the Fresnel rim (see the module's notes). Without
        it the edge lies outside the tangent and the ball comes out too close.

    Raises
    ------
    CalibrationError
        Too few edge points, or rays that do not graze one ball.
    """
    pts = np.asarray(silhouette.points, dtype=float)
    if len(pts) < 10:
        raise CalibrationError(f"only {len(pts)} silhouette points: at least 10 are needed")
    k_inv = np.linalg.inv(np.asarray(camera_matrix, dtype=float))
    radius = float(radius_m)
    d = _rays(k_inv, pts)
    result = _tangent_fit(d, _cone_guess(d, radius), radius)
    shift, use = np.zeros(len(pts)), pts
    if ball_index is not None and silhouette.window_px[0] > 0:
        normals = np.asarray(silhouette.normals, dtype=float)
        for _ in range(iterations):  # the rim's shift depends on the ball's distance
            shift = _rim_shift(silhouette, k_inv, radius / float(np.linalg.norm(result.x)), ball_index)
            use = pts - shift[:, None] * normals
            result = _tangent_fit(_rays(k_inv, use), result.x, radius)
    centre, residuals = result.x, result.fun
    s2 = float(residuals @ residuals) / max(len(pts) - 3, 1)
    try:
        covariance = s2 * np.linalg.inv(result.jac.T @ result.jac)
    except np.linalg.LinAlgError:
        raise CalibrationError("the silhouette does not constrain the ball's centre (degenerate geometry)") from None
    if not np.all(np.isfinite(centre)) or centre[2] <= radius:
        raise CalibrationError("the silhouette rays do not graze a ball in front of the camera")
    # The naive answer, for comparison: the ellipse's centre taken for the ball's.
    axis = _rays(k_inv, np.asarray([silhouette.ellipse.centre]))[0]
    half = float(np.median(np.arccos(np.clip(_rays(k_inv, use) @ axis, -1.0, 1.0))))
    fit = BallFit(
        centre_camera=centre,
        sigma_camera=np.sqrt(np.diag(covariance)),
        covariance_camera=covariance,
        residuals=residuals,
        radius_m=radius,
        naive_centre_camera=axis * radius / math.sin(half),
        rim_shift_px=float(np.median(shift)),
        points_used=len(pts),
    )
    if extrinsics is not None:
        rot, t = (np.asarray(x, dtype=float) for x in extrinsics)
        fit.centre_rig = rot.T @ (centre - t)
        fit.sigma_rig = np.sqrt(np.diag(rot.T @ covariance @ rot))
    return fit


def calibrate_ball(image, rig: Rig, *, method: str = "ellipse") -> BallFit:
    """Silhouette and centre in one call, with the rig's intrinsics, extrinsics and ball."""
    silhouette = detect_silhouette(image, method=method)
    fit = solve_ball_centre(
        silhouette,
        rig.camera.camera_matrix(),
        rig.ball.radius_m,
        extrinsics=rig.camera.pose.extrinsics(),
        ball_index=(rig.ball.n, rig.ball.k),
    )
    fit.extra["silhouette"] = silhouette
    return fit


def compare_with_rig(fit: BallFit, rig: Rig) -> dict:
    """The measured centre against the rig description's, in millimetres.

    Returns ``measured_mm`` and ``described_mm`` (rig frame), ``discrepancy_mm`` (measured
    minus described, rig frame), ``discrepancy_camera_mm`` (the same along the camera's
    axes: z is the depth), ``distance_mm``, ``sigma_mm`` (the measurement's 1-sigma per rig
    axis) and ``significance`` (the distance over the uncertainty along it).
    """
    rot, t = rig.camera.pose.extrinsics()
    measured = rot.T @ (np.asarray(fit.centre_camera) - t)
    described = np.asarray(rig.ball.centre_m, dtype=float)
    delta = measured - described
    distance = float(np.linalg.norm(delta))
    cov_rig = rot.T @ fit.covariance_camera @ rot
    if distance > 0:
        along = delta / distance
        sigma_along = math.sqrt(max(float(along @ cov_rig @ along), 1e-300))
    else:
        sigma_along = float("nan")
    return {
        "measured_mm": (measured * 1e3).tolist(),
        "described_mm": (described * 1e3).tolist(),
        "discrepancy_mm": (delta * 1e3).tolist(),
        "discrepancy_camera_mm": ((rot @ delta) * 1e3).tolist(),
        "distance_mm": distance * 1e3,
        "sigma_mm": (np.sqrt(np.diag(cov_rig)) * 1e3).tolist(),
        "significance": distance / sigma_along if distance > 0 else 0.0,
    }


# --- what a wrong ball position costs -------------------------------------------------------------
def _wrapped(angle: np.ndarray) -> np.ndarray:
    return np.abs((angle + math.pi) % (2.0 * math.pi) - math.pi)


def angle_sensitivity(
    rig: Rig, light_pose: Pose, shift_m: float = 1e-3, *, plane_radius_m: float | None = None, max_pixels: int = 250_000
) -> dict:
    """How far the recovered outgoing angles move when the ball is ``shift_m`` off.

    Chief rays of a grid of pixels on the ball are traced (``processing.trace``) with the
    rig's ball centre and with it shifted by ``shift_m`` along each rig axis; the pixels
    kept are those whose ray lands on the light plane within ``plane_radius_m`` of the
    light's axis in both traces (default: the housing's face, or 20 mm without one).

    Returns per axis (``"x"``, ``"y"``, ``"z"``): the median and largest change of θ, of φ
    (where θ > 5°, φ being undefined on the axis), of the direction itself (the angle
    between the two outgoing rays) in degrees, and of (u, v) in mm; and overall
    ``theta_median_deg`` / ``theta_max_deg`` (the largest over the axes), ``pixels``,
    ``shift_mm``.
    """

    if not shift_m > 0:
        raise CalibrationError(f"shift_m must be positive, got {shift_m!r}")
    radius = plane_radius_m if plane_radius_m is not None else (rig.light.housing_radius_m or 0.02)
    geometry = RigGeometry.from_rig(rig)
    cols, rows = ball_pixel_grid(geometry, max_pixels)
    base = trace_pixels(geometry, light_pose, cols, rows)
    on_light = base.valid & (np.hypot(base.u, base.v) <= radius)
    # Only the pixels that see the light are traced again (a fraction of the ball's).
    cols, rows = np.asarray(cols, float).ravel()[on_light], np.asarray(rows, float).ravel()[on_light]
    base_theta, base_phi, base_u, base_v = base.theta[on_light], base.phi[on_light], base.u[on_light], base.v[on_light]

    def direction(theta, phi):
        return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)

    out: dict = {"shift_mm": shift_m * 1e3, "plane_radius_mm": radius * 1e3}
    pixels = []
    for i, name in enumerate("xyz"):
        centre = np.asarray(rig.ball.centre_m, dtype=float).copy()
        centre[i] += shift_m
        moved = trace_pixels(RigGeometry.from_rig(rig, ball_centre=centre), light_pose, cols, rows)
        use = moved.valid
        if not use.any():
            raise CalibrationError(
                f"no pixel of the ball sees the light within {radius * 1e3:.0f} mm of its axis at this pose"
            )
        d_theta = np.degrees(np.abs(moved.theta[use] - base_theta[use]))
        off_axis = base_theta[use] > math.radians(5.0)
        d_phi = np.degrees(_wrapped(moved.phi[use] - base_phi[use]))[off_axis]
        cosang = np.clip(
            np.sum(direction(moved.theta[use], moved.phi[use]) * direction(base_theta[use], base_phi[use]), axis=1),
            -1,
            1,
        )
        d_dir = np.degrees(np.arccos(cosang))
        d_uv = np.hypot(moved.u[use] - base_u[use], moved.v[use] - base_v[use]) * 1e3
        out[name] = {
            "theta_median_deg": float(np.median(d_theta)),
            "theta_max_deg": float(d_theta.max()),
            "phi_median_deg": float(np.median(d_phi)) if d_phi.size else float("nan"),
            "phi_max_deg": float(d_phi.max()) if d_phi.size else float("nan"),
            "direction_median_deg": float(np.median(d_dir)),
            "direction_max_deg": float(d_dir.max()),
            "uv_median_mm": float(np.median(d_uv)),
            "uv_max_mm": float(d_uv.max()),
            "pixels": int(use.sum()),
        }
        pixels.append(int(use.sum()))
    out["theta_median_deg"] = max(out[a]["theta_median_deg"] for a in "xyz")
    out["theta_max_deg"] = max(out[a]["theta_max_deg"] for a in "xyz")
    out["pixels"] = min(pixels)
    return out

"""The pinhole's transmission in its own plane: a circle, an ellipse (either with a rough edge) or
a mask image, sampled as the area fraction of each cell of a grid (what the Fresnel integral of
:mod:`~sim_devices.optics.fresnel` needs to resolve the edge).

Coordinates are the camera's aperture plane seen from the sensor looking out through the
pinhole (x along the image's columns, y along its rows), in metres from the hole's centre.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from drivers.config_files import MAX_BINARY_BYTES, read_input_bytes
from drivers.contracts.rig import Camera, RigError

#: Samples of the edge's radius over a turn (the rough edge is interpolated from them).
EDGE_TABLE = 4096


@dataclass(frozen=True)
class ApertureShape:
    """A pinhole: an ellipse of ``semi_axes`` (a circle when equal) turned by ``angle`` (radians,
    from +x towards +y), optionally with a rough edge; or a transmission ``mask`` (rows along y)
    of ``mask_pixel`` metres a pixel, centred on its transmission-weighted centroid.

    The rough edge moves the boundary radially by ``δ(φ)``, a seeded stationary Gaussian process
    along the edge with the covariance ``σ² exp(−s²/2ℓ²)`` in arc length ``s`` (``σ`` the RMS,
    ``ℓ`` the correlation length): a sum of the edge's harmonics ``k ≥ 2`` with random phases and
    amplitudes of variance ``∝ exp(−(kℓ/R)²/2)``, the Gaussian's spectral density (Wiener–Khinchin),
    scaled to exactly ``σ`` RMS. Harmonics 0 and 1 are left out: they would change the hole's size
    and move its centre, which the rig gives separately.
    """

    semi_axes: tuple[float, float]
    angle: float = 0.0
    roughness_rms: float = 0.0
    roughness_correlation: float = 5e-6
    roughness_seed: int = 0
    mask: np.ndarray | None = field(default=None, compare=False, repr=False)  # its summed-area table
    mask_pixel: float = 0.0
    mask_centre: tuple[float, float] = (0.0, 0.0)  # the centroid, in the mask's pixels
    mask_digest: str = ""

    # --- construction -------------------------------------------------------------------------
    @classmethod
    def circle(cls, diameter: float, **rough: Any) -> ApertureShape:
        return cls((diameter / 2.0, diameter / 2.0), **rough)

    @classmethod
    def ellipse(cls, axes: tuple[float, float], angle: float = 0.0, **rough: Any) -> ApertureShape:
        """An ellipse of full ``axes`` (diameters), its first axis ``angle`` radians from +x."""
        return cls((axes[0] / 2.0, axes[1] / 2.0), angle, **rough)

    @classmethod
    def from_mask(cls, transmission: np.ndarray, pixel: float) -> ApertureShape:
        """A mask of transmissions in [0, 1] (rows along y), ``pixel`` metres a pixel."""
        t = np.clip(np.asarray(transmission, dtype=float), 0.0, 1.0)
        if t.ndim != 2 or not np.any(t > 0):
            raise ValueError("an aperture mask must be a 2-D image that transmits somewhere")
        rows, cols = np.indices(t.shape)
        # Pixel (i, j) covers [j, j+1) × [i, i+1) in the mask's pixel units: its centre is +0.5.
        cx, cy = float((t * (cols + 0.5)).sum() / t.sum()), float((t * (rows + 0.5)).sum() / t.sum())
        lit_rows, lit_cols = np.nonzero(t > 0)
        reach = max(float(np.hypot(lit_cols + dx - cx, lit_rows + dy - cy).max()) for dx in (0, 1) for dy in (0, 1))
        table = np.zeros((t.shape[0] + 1, t.shape[1] + 1))
        table[1:, 1:] = t.cumsum(0).cumsum(1)  # table[i, j]: the sum over rows < i and columns < j
        digest = hashlib.sha1(t.tobytes() + repr((t.shape, pixel)).encode()).hexdigest()
        radius = reach * pixel
        return cls((radius, radius), mask=table, mask_pixel=pixel, mask_centre=(cx, cy), mask_digest=digest)

    @classmethod
    def from_rig(cls, camera: Camera) -> ApertureShape:
        """The rig's ``[camera.aperture]``; a mask is read from its PNG file."""
        spec = camera.aperture
        rough = {
            "roughness_rms": spec.edge_roughness_rms_m,
            "roughness_correlation": spec.edge_correlation_m,
            "roughness_seed": spec.roughness_seed,
        }
        if spec.shape == "ellipse" and spec.axes_m is not None:
            return cls.ellipse(spec.axes_m, math.radians(spec.angle_deg), **rough)
        if spec.shape == "mask" and spec.mask is not None and spec.mask_pixel_m is not None:
            return cls.from_mask(read_mask(spec.mask), spec.mask_pixel_m)
        return cls.circle(camera.aperture_diameter_m, **rough)

    # --- properties -----------------------------------------------------------------------------
    @property
    def radius(self) -> float:
        """A radius that holds the whole hole (metres)."""
        return max(self.semi_axes) + 4.0 * self.roughness_rms

    @property
    def finest_detail(self) -> float:
        """The smallest length the sampling must resolve besides the edge (the rough edge's
        correlation length), or ``inf``. (A mask's pixels need not be: each cell takes the exact
        mean of the image over it, as it takes a circle's area fraction.)"""
        return self.roughness_correlation if self.roughness_rms > 0 else math.inf

    # --- sampling -------------------------------------------------------------------------------
    def transmission(self, x: np.ndarray, y: np.ndarray, cell: float) -> np.ndarray:
        """The mean transmission over square cells of side ``cell`` centred at ``(x, y)``.

        Ellipses: the cell's area fraction inside the edge, ``clip(1/2 − d/cell, 0, 1)`` with
        ``d`` the signed distance to the edge along its normal (exact for a straight edge
        parallel to a side of the cell; second order in ``cell`` over a curved one). Masks: the
        exact mean of the piecewise-constant image over the cell (its summed-area table,
        interpolated bilinearly, is the image's integral).
        """
        if self.mask is not None:
            return self._mask_transmission(x, y, cell)
        r = np.hypot(x, y)
        phi = np.arctan2(y, x)
        edge, slope = self._edge(phi)
        distance = (r - edge) / np.sqrt(1.0 + (slope / np.maximum(edge, 1e-30)) ** 2)
        return np.clip(0.5 - distance / cell, 0.0, 1.0)

    def area(self) -> float:
        """The hole's transmitting area in m² (the transmission's integral)."""
        if self.mask is not None:
            return float(self.mask[-1, -1]) * self.mask_pixel**2
        phi = np.linspace(0.0, 2.0 * math.pi, EDGE_TABLE, endpoint=False)
        edge, _ = self._edge(phi)
        return float(0.5 * np.mean(edge**2) * 2.0 * math.pi)

    # --- the edge ---------------------------------------------------------------------------------
    def _edge(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The edge's radius ``R(φ)`` and its derivative ``dR/dφ`` at polar angles ``phi``."""
        a, b = self.semi_axes
        psi = phi - self.angle
        c, s = np.cos(psi), np.sin(psi)
        q = (b * c) ** 2 + (a * s) ** 2
        radius = a * b / np.sqrt(q)
        slope = -0.5 * a * b * q**-1.5 * 2.0 * c * s * (a * a - b * b)
        if self.roughness_rms > 0:
            table, table_slope = self._roughness_table()
            grid = np.linspace(0.0, 2.0 * math.pi, EDGE_TABLE + 1)
            wrapped = np.mod(phi, 2.0 * math.pi)
            radius = radius + np.interp(wrapped, grid, np.append(table, table[0]))
            slope = slope + np.interp(wrapped, grid, np.append(table_slope, table_slope[0]))
        return radius, slope

    def _roughness_table(self) -> tuple[np.ndarray, np.ndarray]:
        """δ(φ) and dδ/dφ over :data:`EDGE_TABLE` angles (see the class's docstring)."""
        mean_radius = math.sqrt(self.semi_axes[0] * self.semi_axes[1])
        reach = mean_radius / self.roughness_correlation
        k = np.arange(2, max(3, int(math.ceil(6.0 * reach)) + 1))
        variance = np.exp(-0.5 * (k / reach) ** 2)
        rng = np.random.default_rng(self.roughness_seed)
        amplitude = np.sqrt(variance) * rng.standard_normal((2, k.size))
        phi = np.linspace(0.0, 2.0 * math.pi, EDGE_TABLE, endpoint=False)[:, None]
        cos, sin = np.cos(k * phi), np.sin(k * phi)
        delta = cos @ amplitude[0] + sin @ amplitude[1]
        slope = (-sin * k) @ amplitude[0] + (cos * k) @ amplitude[1]
        scale = self.roughness_rms / math.sqrt(float(np.mean(delta**2)))
        return delta * scale, slope * scale

    def _mask_transmission(self, x: np.ndarray, y: np.ndarray, cell: float) -> np.ndarray:
        assert self.mask is not None
        half = 0.5 * cell / self.mask_pixel
        u, v = x / self.mask_pixel + self.mask_centre[0], y / self.mask_pixel + self.mask_centre[1]

        def integral(
            uu: np.ndarray, vv: np.ndarray
        ) -> np.ndarray:  # the image's integral over [0, uu] × [0, vv], in pixels
            at = [np.ravel(vv), np.ravel(uu)]
            return ndimage.map_coordinates(self.mask, at, order=1, mode="nearest").reshape(np.shape(uu))

        total = integral(u + half, v + half) - integral(u - half, v + half) - integral(u + half, v - half)
        total += integral(u - half, v - half)
        return np.clip(total / (2.0 * half) ** 2, 0.0, 1.0)


def read_mask(path: str | Path) -> np.ndarray:
    """A greyscale PNG's transmission: its grey level over the format's full scale (8 or 16 bits).

    Raises :class:`~drivers.contracts.rig.RigError` naming ``camera.aperture.mask`` when the file
    cannot be read or is not a greyscale image.
    """
    data = read_input_bytes(path, "aperture mask", RigError, field="camera.aperture.mask", limit=MAX_BINARY_BYTES)
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise RigError(f"camera.aperture.mask: cannot read {path} as an image")
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise RigError(f"camera.aperture.mask: {path} is not an 8- or 16-bit greyscale image")
    transmission = image.astype(float) / (255.0 if image.dtype == np.uint8 else 65535.0)
    if not np.any(transmission > 0):
        raise RigError(f"camera.aperture.mask: {path} transmits nowhere (an all-black image)")
    return transmission

"""The camera's rays on the superpixel grid, where they meet the mesh, and the silhouettes and depth steps."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np
from scipy.ndimage import binary_dilation

from drivers.contracts.rig import Camera, Rig

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger("mirrorgonio.processing")

#: Sensor-plane coordinates: one number, or an array of them.
_Plane = TypeVar("_Plane", float, np.ndarray)


@dataclass(frozen=True)
class SuperpixelRays:
    centre: np.ndarray
    directions: np.ndarray  # (H2, W2, 3), rig frame, unit
    cos4: np.ndarray  # (H2, W2)
    angle: float  # a superpixel's angular size at the axis, radians
    optical_axis: np.ndarray

    @classmethod
    def of(cls, camera: Camera, shape: tuple[int, int]) -> SuperpixelRays:
        K = camera.camera_matrix()
        R, t = camera.pose.extrinsics()
        h2, w2 = shape
        rows, cols = np.mgrid[0:h2, 0:w2]
        px = 2.0 * cols + 0.5  # the centre of the 2x2 tile, pixel centres at integers
        py = 2.0 * rows + 0.5
        x = (px - K[0, 2]) / K[0, 0]
        y = (py - K[1, 2]) / K[1, 1]
        in_camera = np.stack([x, y, np.ones_like(x)], axis=-1)
        in_rig = in_camera @ R  # R.T @ d
        directions = in_rig / np.linalg.norm(in_rig, axis=-1, keepdims=True)
        cos4 = aperture_mean_cos4(x, y, camera.aperture_diameter_m / 2.0, camera.sensor_distance_m)
        return cls(-R.T @ np.asarray(t, float), directions, cos4, 2.0 / K[0, 0], R[2].copy())


def aperture_mean_cos4(x: _Plane, y: _Plane, aperture_radius: float, sensor_distance: float) -> _Plane:
    """``⟨cos⁴β⟩`` over a uniform circular aperture for sensor points at ``(x, y)·f``.

    A pixel gathers light through the whole aperture and each ray's fall-off is the
    ``cos⁴β`` of its own sensor-side segment; with ``q = 1 + x² + y²`` and ``a = R/f``
    (``R`` the aperture's radius, ``f`` the sensor distance), the mean over the disc to
    second order in ``a`` (the next term is ``O(a⁴)``: 1.5e-5 at f/8) is::

        ⟨cos⁴β⟩ = 1/q² + a²·(3(x² + y²)/q⁴ − 1/q³)

    The chief ray's ``1/q²`` alone is 0.4 % high on the axis of an f/8 lens.

    Examples
    --------
    On the axis, ``1 - a²``:

    >>> float(aperture_mean_cos4(0.0, 0.0, aperture_radius=1e-3, sensor_distance=1e-2))
    0.99
    """
    rho2 = x * x + y * y
    q = 1.0 + rho2
    a2 = (aperture_radius / sensor_distance) ** 2
    return 1.0 / q**2 + a2 * (3.0 * rho2 / q**4 - 1.0 / q**3)


def camera_from(camera: Camera | Rig) -> Camera:
    """Accept a rig's ``Camera`` or a whole ``Rig``."""
    return cast(Camera, getattr(camera, "camera", camera))


def _plane_distance(
    mesh: trimesh.Trimesh, faces: np.ndarray, origins: np.ndarray, directions: np.ndarray
) -> np.ndarray:
    """Distance along each ray to the plane of the given face (float64, exact for flat faces)."""
    normals = mesh.face_normals[faces]
    v0 = mesh.vertices[mesh.faces[faces, 0]]
    denom = np.einsum("ij,ij->i", normals, directions)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.einsum("ij,ij->i", normals, v0 - origins) / denom


def first_hits(mesh: trimesh.Trimesh, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First face met by each ray (−1 for none) and the distance to it (``inf`` for none)."""
    faces = np.asarray(mesh.ray.intersects_first(origins, directions), dtype=np.int64)
    dist = np.full(len(origins), np.inf)
    hit = faces >= 0
    if hit.any():
        dist[hit] = _plane_distance(mesh, faces[hit], origins[hit], directions[hit])
    return faces, dist


def dilate(mask: np.ndarray, iterations: int) -> np.ndarray:
    if iterations <= 0 or not mask.any():
        return mask.copy()

    return binary_dilation(mask, structure=np.ones((3, 3), bool), iterations=int(iterations))


def edge_core(
    hit: np.ndarray,
    depth: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    directions: np.ndarray,
    centre: np.ndarray,
    angle: float,
    tolerance: float,
) -> np.ndarray:
    """Silhouettes and depth discontinuities on the superpixel grid (before dilation).

    A hit pixel next to a miss is on a silhouette. Two neighbouring hits are discontinuous
    when the depth of each differs from where its ray meets the other's face plane by more
    than ``tolerance`` superpixel footprints (a smooth surface, even with creases between
    flat faces, is explained by one of the two planes; an occlusion by neither).
    """
    core = np.zeros(hit.shape, bool)
    pad = np.pad(hit, 1, constant_values=True)  # beyond the image is unknown, not background
    neighbour_missing = ~pad[:-2, 1:-1] | ~pad[2:, 1:-1] | ~pad[1:-1, :-2] | ~pad[1:-1, 2:]
    core |= hit & neighbour_missing
    for axis in (0, 1):
        a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        both = hit[a] & hit[b]

        def predicted(src: Any, dst: Any) -> np.ndarray:
            n = normals[src]
            denom = np.einsum("...k,...k->...", n, directions[dst])
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.einsum("...k,...k->...", n, points[src] - centre) / denom

        err_ab = np.abs(depth[b] - predicted(a, b))
        err_ba = np.abs(depth[a] - predicted(b, a))
        err = np.fmin(err_ab, err_ba)
        scale = tolerance * angle * np.fmax(depth[a], depth[b])
        jump = both & ~(err <= scale)  # NaN (a ray parallel to a face) counts as a jump
        core[a] |= jump
        core[b] |= jump
    return core


def superpixel_any(mask: np.ndarray) -> np.ndarray:
    """(..., H/2, W/2): any of each 2x2 tile's sites set."""
    h, w = mask.shape[-2:]
    m = mask[..., : h - h % 2, : w - w % 2]
    return cast(np.ndarray, m.reshape(*m.shape[:-2], h // 2, 2, w // 2, 2).any(axis=(-3, -1)))  # stubs: an array

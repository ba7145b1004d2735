"""Objects for the reflectance simulation: shipped meshes, mesh files, reflectance truth.

The simulated camera photographs an object in place of the ball when the rig has an
``[object]`` section (``docs/rig.md``). This module provides

- the shipped meshes (:func:`vase_mesh`, :func:`relief_plate_mesh`), written as OBJ with
  texture coordinates to ``rigs/objects/`` by ``python -m sim_devices.objects``;
- :class:`ObjectGeometry`: the mesh *as trimesh reads it from the file the rig names*,
  placed in the rig frame (``x_rig = R·(units_m·x_mesh) + t``), with its flat face normals
  and per-vertex UVs. The processing reads the same file with trimesh, so both sides see
  the same polyhedron whatever trimesh does on loading;
- the surface truth (:class:`SurfaceTruth`, TOML files in ``sim_devices/surfaces/``): a
  base albedo per channel (R, G, B) and finish (GGX roughness, dielectric specular weight
  and index, metalness: :mod:`sim_devices.brdf`), painted elliptical patches in UV space
  with their own albedo and finish, and, for the older tests of highlight rejection, an
  optional energy-normalised Blinn–Phong lobe;
- :func:`surface_truth_at`: the truth albedo at rig-frame surface points, and whether each
  lies in the base-albedo region well away from any patch (for the reflectance benchmark);
  :func:`surface_finish_at` the truth finish there.

UV conventions of the shipped meshes (object frame; ``up`` = +y):

- vase: ``u = azimuth / 2π`` with the azimuth measured about +y from the object's −z side
  through +x, so ``u = 0.5`` faces +z (the default camera), ``u = 0.25`` faces +x and the
  seam ``u = 0/1`` faces away from the camera; ``v`` is the height fraction (0 at the foot,
  1 at the lip). The visible front half is ``0.25 < u < 0.75``.
- relief plate: ``u = (x − x_min) / width``, ``v = (y − y_min) / height``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Annotated, Self

import cv2
import numpy as np
import OpenEXR
import trimesh
from numpy.typing import ArrayLike
from pydantic import Field, PositiveFloat, PrivateAttr, model_validator
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from drivers.config_files import MAX_BINARY_BYTES, ConfigModel, check_input_file, load_model
from drivers.contracts.rig import RIGS_DIR, Rig
from sim_devices.brdf import Finish, fresnel_dielectric

SURFACES_DIR = Path(__file__).resolve().parent / "surfaces"
OBJECTS_DIR = RIGS_DIR / "objects"


class SurfaceError(ValueError):
    """An unreadable or impossible surface truth file (one line: file, field, cause)."""


class ObjectError(ValueError):
    """An object mesh that cannot be read or used (one line: file, cause)."""


# --- surface truth ---------------------------------------------------------------------------
Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
Albedo = tuple[Fraction, Fraction, Fraction]


class SurfaceFinish(ConfigModel):
    """The gloss of a region (:mod:`sim_devices.brdf`); the default is matte.

    ``roughness`` is GGX's α (0.02: a polished coat, 0.5: a satin one); ``specular`` the
    dielectric's specular weight (0 matte, 1 a full glaze or varnish) with its index
    ``ior``; ``metalness`` 1 makes the region a conductor whose albedo is its F₀.
    """

    roughness: Annotated[float, Field(ge=0.02, le=1.0)] = 0.5
    specular: Fraction = 0.0
    ior: Annotated[float, Field(ge=1.0, le=3.0)] = 1.5
    metalness: Fraction = 0.0

    @property
    def glossy(self) -> bool:
        return self.specular > 0.0 or self.metalness > 0.0


class Patch(ConfigModel):
    """A painted patch: the inside of an ellipse in UV space, axis-aligned.

    ``radius_uv`` is one radius, or the semi-axes along u and along v. Without a
    ``finish`` the patch keeps the surface's base finish.
    """

    name: str = ""
    centre_uv: tuple[float, float]
    radius_uv: PositiveFloat | tuple[PositiveFloat, PositiveFloat]
    albedo: Albedo
    finish: SurfaceFinish | None = None

    @property
    def radii(self) -> tuple[float, float]:
        r = self.radius_uv
        return (float(r), float(r)) if isinstance(r, (int, float)) else (float(r[0]), float(r[1]))


class Specular(ConfigModel):
    """Energy-normalised Blinn–Phong lobe, channel-neutral:
    ``L_spec = k_s · (m + 8) / (8π) · (n·h)^m · E`` per emitter (E its irradiance)."""

    k_s: Fraction
    exponent: PositiveFloat


class SurfaceMaps(ConfigModel):
    """Images of the surface's parameters in the mesh's UV layout; paths relative to the surface file.

    u runs along an image's columns and v up its rows (row 0 is v = 1, as OBJ and glTF place
    textures); between texel centres the value is bilinear, u wraps and v clamps. A map sets
    its parameter everywhere, over the base and the patches (which still paint the
    parameters without a map). ``albedo``: RGB, a PNG in sRGB (8 or 16 bit) or a linear
    OpenEXR; ``roughness`` (GGX α, 0.02–1), ``specular`` (the coat's weight, 0–1) and
    ``metalness`` (0–1): one channel, a PNG whose value over its full scale is the number,
    or a linear OpenEXR (channel ``Y``, or its only one).
    """

    albedo: str | None = None
    roughness: str | None = None
    specular: str | None = None
    metalness: str | None = None


#: Each map's channels and the range its values must lie in.
MAP_CHANNELS = {
    "albedo": (3, 0.0, 1.0),
    "roughness": (1, 0.02, 1.0),
    "specular": (1, 0.0, 1.0),
    "metalness": (1, 0.0, 1.0),
}


def read_surface_map(path: Path, name: str) -> np.ndarray:
    """One map as float (H, W, channels), linear; a one-line :class:`SurfaceError` naming the
    field and the file for a missing, unreadable, wrongly shaped or out-of-range image."""
    where = f"maps.{name}: {path}"
    check_input_file(path, "surface map", SurfaceError, field=f"maps.{name}", limit=MAX_BINARY_BYTES)
    channels, lo, hi = MAP_CHANNELS[name]
    if path.suffix.lower() == ".exr":
        try:
            with OpenEXR.File(str(path)) as exr:  # the pixels are the file's only while it is open
                layers = exr.channels()
                key = "RGB" if channels == 3 and "RGB" in layers else ("Y" if "Y" in layers else next(iter(layers)))
                image = np.array(layers[key].pixels, dtype=float)
        except RuntimeError as exc:  # what OpenEXR raises for a file it cannot read
            raise SurfaceError(f"{where}: not a readable OpenEXR file ({exc})") from None
    elif path.suffix.lower() == ".png":
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise SurfaceError(f"{where}: not a readable PNG file")
        image = raw.astype(float) / (65535.0 if raw.dtype == np.uint16 else 255.0)
        if image.ndim == 3:
            image = image[..., 2::-1] if image.shape[2] >= 3 else image[..., :1]  # OpenCV's BGR(A)
        if name == "albedo":
            image = np.where(image <= 0.04045, image / 12.92, ((image + 0.055) / 1.055) ** 2.4)  # sRGB
    else:
        raise SurfaceError(f"{where}: a map is a .png or an .exr file")
    image = image.reshape(image.shape[0], image.shape[1], -1)
    if image.shape[2] != channels:
        raise SurfaceError(f"{where}: {image.shape[2]} channels, the {name} map needs {channels}")
    if not (np.all(np.isfinite(image)) and image.min() >= lo - 1e-6 and image.max() <= hi + 1e-6):
        raise SurfaceError(f"{where}: values {image.min():.4g} to {image.max():.4g}, outside {lo:g}-{hi:g}")
    return np.clip(image, lo, hi)


def sample_uv(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear values (N, channels) of a UV map at points ``uv`` (N, 2): u wraps, v clamps."""
    h, w = image.shape[:2]
    x = np.asarray(uv[:, 0], float) * w - 0.5
    y = (1.0 - np.asarray(uv[:, 1], float)) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    xs = [np.mod(x0, w).astype(np.int64), np.mod(x0 + 1, w).astype(np.int64)]
    ys = [np.clip(y0, 0, h - 1).astype(np.int64), np.clip(y0 + 1, 0, h - 1).astype(np.int64)]
    top = image[ys[0], xs[0]] * (1 - fx) + image[ys[0], xs[1]] * fx
    bottom = image[ys[1], xs[0]] * (1 - fx) + image[ys[1], xs[1]] * fx
    return top * (1 - fy) + bottom * fy


class SurfaceTruth(ConfigModel):
    """The reflectance truth of a simulated object's surface.

    The diffuse part is Lambertian with albedo ``ρ`` per channel (R, G, B): the base albedo
    everywhere except inside the patches (a later patch paints over an earlier one). The
    microfacet lobe follows the base ``finish`` and each patch's own. ``maps`` set any
    parameter from an image in UV space (:class:`SurfaceMaps`), read by :func:`load_surface`.
    """

    name: str = "surface"
    description: str = ""
    base_albedo: Albedo
    finish: SurfaceFinish = Field(default_factory=SurfaceFinish)
    patches: list[Patch] = Field(default_factory=list)
    specular: Specular | None = None
    maps: SurfaceMaps | None = None
    _images: dict[str, np.ndarray] = PrivateAttr(default_factory=dict)

    def read_maps(self, surface_file: Path) -> SurfaceTruth:
        """Read the :attr:`maps` (paths relative to ``surface_file``'s folder) and check the energy they allow."""
        if self.maps is None:
            return self
        folder = surface_file.parent
        for name in MAP_CHANNELS:
            relative = getattr(self.maps, name)
            if relative is not None:
                try:
                    self._images[name] = read_surface_map(folder / relative, name)
                except SurfaceError as exc:  # said from the surface file the map belongs to
                    raise SurfaceError(f"{surface_file}: {exc}") from None
        if self.specular is not None and self._images:
            raise SurfaceError(
                f"{surface_file}: maps: a Blinn-Phong lobe (specular) beside maps; give one or the other"
            )
        albedo = self._images.get("albedo")
        if albedo is not None:  # every albedo texel under the finish there (:meth:`finish_at`)
            h, w = albedo.shape[:2]
            v, u = np.mgrid[0:h, 0:w]
            uv = np.column_stack([((u + 0.5) / w).ravel(), (1.0 - (v + 0.5) / h).ravel()])
            finish = self.finish_at(uv)
            coat = finish.specular * fresnel_dielectric(np.ones(len(uv)), finish.ior)
            total = (1.0 - finish.metalness) * (albedo.reshape(-1, 3).max(axis=1) + coat)
            worst = int(np.argmax(total))
            if total[worst] > 1.0 + 1e-6:
                raise SurfaceError(
                    f"{surface_file}: maps.albedo: albedo {albedo.reshape(-1, 3)[worst].max():.3g} plus a coat's "
                    f"{coat[worst]:.3g} at uv ({uv[worst, 0]:.3f}, {uv[worst, 1]:.3f}) reflects more than it receives"
                )
        return self

    def _finishes(self) -> list[SurfaceFinish]:
        return [self.finish] + [p.finish or self.finish for p in self.patches]

    @property
    def varies(self) -> bool:
        """Whether anything changes over the surface (patches or maps): it then needs UVs."""
        return bool(self.patches) or bool(self._images)

    @model_validator(mode="after")
    def _energy(self) -> Self:
        if self.specular is not None:
            if self.glossy:
                raise ValueError("specular: a Blinn-Phong lobe beside a glossy finish; give one or the other")
            top = max([max(self.base_albedo)] + [max(p.albedo) for p in self.patches])
            if top + self.specular.k_s > 1.0:
                raise ValueError(
                    f"specular.k_s: albedo {top:g} plus k_s {self.specular.k_s:g} reflects more than it receives"
                )
        regions = [("finish", self.base_albedo, self.finish)]
        regions += [(f"patches[{i}].finish", p.albedo, p.finish or self.finish) for i, p in enumerate(self.patches)]
        for where, albedo, finish in regions:
            coat = finish.specular * float(fresnel_dielectric(1.0, finish.ior))
            total = (1.0 - finish.metalness) * (max(albedo) + coat)
            if total > 1.0:
                raise ValueError(
                    f"{where}: albedo {max(albedo):g} plus the coat's {coat:.3g} at normal incidence "
                    "reflects more than it receives"
                )
        return self

    @property
    def glossy(self) -> bool:
        """True where any region has a microfacet lobe."""
        mapped = any(float(self._images[k].max()) > 0 for k in ("specular", "metalness") if k in self._images)
        return mapped or self.finish.glossy or any(p.finish is not None and p.finish.glossy for p in self.patches)

    def patch_index(self, uv: np.ndarray) -> np.ndarray:
        """Index of the patch that paints each UV point (the last one wins), −1 for the base."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        index = np.full(len(uv), -1, dtype=np.int64)
        for i, patch in enumerate(self.patches):
            (cu, cv), (ru, rv) = patch.centre_uv, patch.radii
            inside = ((uv[:, 0] - cu) / ru) ** 2 + ((uv[:, 1] - cv) / rv) ** 2 <= 1.0
            index[inside] = i
        return index

    def albedo_at(self, uv: np.ndarray | None, count: int | None = None) -> np.ndarray:
        """Diffuse albedo (N, 3) at UV points (``uv`` None: the base everywhere, ``count`` points)."""
        if uv is None:
            return np.broadcast_to(np.asarray(self.base_albedo, float), (count or 0, 3)).copy()
        if "albedo" in self._images:
            return sample_uv(self._images["albedo"], np.asarray(uv, float).reshape(-1, 2))
        table = np.array([self.base_albedo] + [p.albedo for p in self.patches], dtype=float)
        return table[self.patch_index(uv) + 1]

    def finish_at(self, uv: np.ndarray | None, count: int | None = None) -> Finish:
        """The finish at UV points (``uv`` None: the base everywhere, ``count`` points)."""
        table = np.array([(f.roughness, f.specular, f.ior, f.metalness) for f in self._finishes()], dtype=float)
        rows = np.zeros(count or 0, np.int64) if uv is None else self.patch_index(uv) + 1
        values = table[rows]
        if uv is not None:
            for column, name in ((0, "roughness"), (1, "specular"), (3, "metalness")):
                if name in self._images:
                    values[:, column] = sample_uv(self._images[name], np.asarray(uv, float).reshape(-1, 2))[:, 0]
        return Finish(roughness=values[:, 0], specular=values[:, 1], ior=values[:, 2], metalness=values[:, 3])

    def uv_distance_to_patches(self, uv: np.ndarray) -> np.ndarray:
        """A lower bound of the UV-space distance from each point to the nearest patch.

        For an ellipse of semi-axes (a, b), a point at normalised radius s > 1 is at least
        ``min(a, b) · (s − 1)`` away; inside a patch the distance is 0. Infinite without patches.
        """
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        out = np.full(len(uv), np.inf)
        for patch in self.patches:
            (cu, cv), (ru, rv) = patch.centre_uv, patch.radii
            s = np.hypot((uv[:, 0] - cu) / ru, (uv[:, 1] - cv) / rv)
            out = np.minimum(out, np.maximum(s - 1.0, 0.0) * min(ru, rv))
        return out


def load_surface(name_or_path: str | Path) -> SurfaceTruth:
    """Load a surface truth by shipped name (``uniform``, ``patches``) or by TOML path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = SURFACES_DIR / f"{name_or_path}.toml"
        if not path.exists():
            shipped = ", ".join(sorted(p.stem for p in SURFACES_DIR.glob("*.toml")))
            raise SurfaceError(f"{name_or_path}: no such surface (shipped: {shipped})")
    return load_model(path, SurfaceTruth, "surface file", SurfaceError).read_maps(path)


# --- shipped meshes ----------------------------------------------------------------------------
# The vase's radius (mm) at height fractions 0..1: a foot, a bulge, a narrow neck and a
# flared lip whose overhang shadows the neck when lit from above.
VASE_PROFILE_MM = (
    (0.00, 12.0),
    (0.10, 15.5),
    (0.30, 19.0),
    (0.50, 17.0),
    (0.68, 11.0),
    (0.80, 8.0),
    (0.88, 9.0),
    (0.95, 12.5),
    (1.00, 16.0),
)

# Gaussian bumps of the relief plate: (x mm, y mm, height mm, sigma mm).
RELIEF_BUMPS_MM = (
    (-18.0, 8.0, 3.0, 4.0),
    (-6.0, -9.0, 2.5, 3.5),
    (5.0, 5.0, 4.0, 5.0),
    (19.0, -8.0, 2.0, 3.0),
    (21.0, 11.0, 3.0, 4.5),
    (-21.0, -11.0, 3.5, 4.0),
)


def _textured(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> trimesh.Trimesh:
    visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv, dtype=float))
    return trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), visual=visual, process=False)


def vase_mesh(
    height_m: float = 0.05,
    profile_mm: Sequence[tuple[float, float]] = VASE_PROFILE_MM,
    segments: int = 120,
    max_turn_deg: float = 2.5,
    max_step_m: float = 0.5e-3,
) -> trimesh.Trimesh:
    """A vase: a surface of revolution about +y, open at the foot and at the lip.

    The profile (radius against height fraction) is a natural cubic spline through
    ``profile_mm``; the object frame's origin is at mid-height on the axis. Rings are
    placed so that consecutive rings differ by at most ``max_turn_deg`` in normal and
    ``max_step_m`` in arc length; ``segments`` facets go around (3° apart by default).
    UVs: ``u = azimuth / 2π`` (0.5 facing +z), ``v`` = height fraction; the seam (u = 0
    and u = 1) has its vertices doubled, one per side.
    """
    t_pts, r_pts = np.asarray(profile_mm, dtype=float).T
    spline = CubicSpline(t_pts, r_pts * 1e-3, bc_type="natural")
    t = np.linspace(0.0, 1.0, 20001)
    r, dr = spline(t), spline(t, 1)
    if np.any(r <= 0):
        raise ValueError("the vase profile reaches the axis")
    dy = height_m  # d(y)/dt
    step = np.hypot(dr, dy) * (t[1] - t[0])
    angle = np.unwrap(np.arctan2(dr, dy))
    measure = np.concatenate(
        [[0.0], np.cumsum(step[1:] / max_step_m + np.abs(np.diff(angle)) / math.radians(max_turn_deg))]
    )
    n_rings = int(math.ceil(measure[-1])) + 1
    t_rings = np.interp(np.linspace(0.0, measure[-1], n_rings), measure, t)
    r_rings = spline(t_rings)
    y_rings = (t_rings - 0.5) * height_m

    u = np.arange(segments + 1) / segments  # the seam is doubled: u = 0 and u = 1
    phi = 2.0 * math.pi * u
    x = r_rings[:, None] * np.sin(phi)[None, :]
    z = -r_rings[:, None] * np.cos(phi)[None, :]
    y = np.broadcast_to(y_rings[:, None], x.shape)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    uv = np.stack(np.broadcast_arrays(u[None, :], t_rings[:, None]), axis=-1).reshape(-1, 2)
    cols = segments + 1
    i, j = np.meshgrid(np.arange(n_rings - 1), np.arange(segments), indexing="ij")
    a = (i * cols + j).ravel()
    b, c, d = a + 1, a + cols + 1, a + cols
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])
    mesh = _textured(vertices, faces, uv)
    # Normals point away from the axis (outwards) by the right-hand rule.
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center * [1, 0, 1])
    if np.median(outward) < 0:
        faces = faces[:, ::-1]
        mesh = _textured(vertices, faces, uv)
    return mesh


def relief_plate_mesh(
    size_m: tuple[float, float] = (0.06, 0.04),
    spacing_m: float = 0.4e-3,
    bumps_mm: Sequence[tuple[float, ...]] = RELIEF_BUMPS_MM,
) -> trimesh.Trimesh:
    """A plate in the object's x–y plane facing +z, with smooth Gaussian bumps.

    ``z = Σ h·exp(−|p − c|² / 2σ²)`` on a regular grid (``spacing_m``), centred on the
    origin; ``bumps_mm=()`` gives a flat plate. UVs: u along x, v along y, 0..1 each.
    """
    width, height = size_m
    nx = int(round(width / spacing_m)) + 1
    ny = int(round(height / spacing_m)) + 1
    xs = np.linspace(-width / 2, width / 2, nx)
    ys = np.linspace(-height / 2, height / 2, ny)
    xg, yg = np.meshgrid(xs, ys)  # rows along y
    zg = np.zeros_like(xg)
    for bx, by, bh, bs in bumps_mm:
        zg += bh * 1e-3 * np.exp(-((xg - bx * 1e-3) ** 2 + (yg - by * 1e-3) ** 2) / (2 * (bs * 1e-3) ** 2))
    vertices = np.stack([xg, yg, zg], axis=-1).reshape(-1, 3)
    uv = np.stack([(xg + width / 2) / width, (yg + height / 2) / height], axis=-1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    a = (i * nx + j).ravel()
    b, c, d = a + 1, a + nx + 1, a + nx
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])  # normals +z
    return _textured(vertices, faces, uv)


def write_obj(path: str | Path, mesh: trimesh.Trimesh, comment: str = "") -> Path:
    """Write a mesh as a plain OBJ (``v``, ``vt``, ``f v/vt``), deterministically.

    Positions are written to 1 nm (``%.9f`` metres), UVs to 1e-7. One texture coordinate
    per vertex, so trimesh reads back the same vertices in the same order.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    uv = _uv_of(mesh)
    lines = [f"# {line}" for line in comment.splitlines()] if comment else []
    lines += [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in np.asarray(mesh.vertices)]
    if uv is not None:
        lines += [f"vt {u:.7f} {v:.7f}" for u, v in uv]
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in np.asarray(mesh.faces) + 1]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in np.asarray(mesh.faces) + 1]
    path.write_text("\n".join(lines) + "\n")
    return path


def _uv_of(mesh: trimesh.Trimesh) -> np.ndarray | None:
    uv = getattr(mesh.visual, "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        return None
    return np.asarray(uv, dtype=float)


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Read a mesh file (PLY, OBJ, STL, ...) with trimesh's defaults, as one mesh."""
    path = Path(path)
    check_input_file(path, "object mesh", ObjectError, limit=MAX_BINARY_BYTES)  # no FIFO, device, directory
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # noqa: BLE001 - trimesh's loaders raise many kinds
        raise ObjectError(f"{path}: cannot read the mesh: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ObjectError(f"{path}: the file holds no triangles")
    return mesh


# --- the object in the rig frame -----------------------------------------------------------------
@dataclass
class ObjectGeometry:
    """The rig's object as a polyhedron in the rig frame.

    ``vertices`` (V, 3) metres in the rig frame, ``faces`` (F, 3), ``normals`` (F, 3) the
    flat face normals (right-hand rule on the face's vertex order, as trimesh computes
    them; a renderer orients them towards the viewer), ``uv`` (V, 2) or None.
    """

    path: Path
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None

    @classmethod
    def from_rig(cls, rig: Rig) -> ObjectGeometry:
        if rig.object is None:
            raise ObjectError(f"{rig.name}: the rig has no [object]")
        mesh = load_mesh(rig.object.mesh)
        pose = rig.object.pose.to_pose()
        vertices = np.asarray(mesh.vertices, float) * rig.object.units_m @ pose.rotation.T + pose.position
        return cls(Path(rig.object.mesh), vertices, np.asarray(mesh.faces, np.int64), _uv_of(mesh))

    @cached_property
    def triangles(self) -> np.ndarray:
        return self.vertices[self.faces]

    @cached_property
    def normals(self) -> np.ndarray:
        tri = self.triangles
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, length, out=np.zeros_like(n), where=length > 0)

    def uv_at(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray | None:
        """UV (N, 2) at barycentric coordinates ``bary`` (N, 3) on ``faces`` (N,)."""
        if self.uv is None:
            return None
        return np.einsum("nk,nkj->nj", bary, self.uv[self.faces[faces]])

    @cached_property
    def uv_metric(self) -> np.ndarray:
        """Per face, the smallest stretch (metres per UV unit) of the UV → surface map.

        0 for faces whose UVs are degenerate (or when the mesh has no UVs).
        """
        if self.uv is None:
            return np.zeros(len(self.faces))
        tri, tuv = self.triangles, self.uv[self.faces]
        dp = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=-1)  # (F, 3, 2)
        duv = np.stack([tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0]], axis=-1)  # (F, 2, 2)
        det = duv[:, 0, 0] * duv[:, 1, 1] - duv[:, 0, 1] * duv[:, 1, 0]
        ok = np.abs(det) > 1e-14
        inv = np.zeros_like(duv)
        inv[ok] = np.linalg.inv(duv[ok])
        jac = dp @ inv  # dP/d(uv), (F, 3, 2)
        out = np.zeros(len(self.faces))
        out[ok] = np.linalg.svd(jac[ok], compute_uv=False)[:, -1]
        return out

    def closest_faces(
        self, points: np.ndarray, candidates: int = 16, chunk: int = 50_000
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest face (N,), barycentric coordinates (N, 3) and distance (N,) of rig-frame points.

        Candidates are the faces with the nearest centroids; the exact point–triangle
        distance picks among them (exact for points on or near the surface).
        """
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        tree = getattr(self, "_centroid_tree", None)
        if tree is None:
            tree = self._centroid_tree = cKDTree(self.triangles.mean(axis=1))
        k = min(candidates, len(self.faces))
        face = np.empty(len(points), np.int64)
        bary = np.empty((len(points), 3))
        dist = np.empty(len(points))
        for s in range(0, len(points), chunk):
            p = points[s : s + chunk]
            _, cand = tree.query(p, k=k)
            cand = np.asarray(cand).reshape(len(p), k)
            q, b = closest_point_on_triangles(self.triangles[cand.ravel()], np.repeat(p, k, axis=0))
            d = np.linalg.norm(q - np.repeat(p, k, axis=0), axis=1).reshape(len(p), k)
            best = np.argmin(d, axis=1)
            rows = np.arange(len(p))
            face[s : s + chunk] = cand[rows, best]
            bary[s : s + chunk] = b.reshape(len(p), k, 3)[rows, best]
            dist[s : s + chunk] = d[rows, best]
        return face, bary, dist


def closest_point_on_triangles(triangles: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point on each triangle (N, 3, 3) to each point (N, 3), and its barycentrics.

    Ericson, *Real-Time Collision Detection*, §5.1.5 (Voronoi regions of the vertices,
    edges and face), vectorised; free of scale-dependent tolerances.
    """
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    p = np.asarray(points, dtype=float)
    ab, ac = b - a, c - a

    def dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", x, y)

    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    bary = np.stack([1.0 - v_in - w_in, v_in, w_in], axis=-1)
    # Later assignments take precedence, in the reverse of Ericson's order of tests.
    regions = [
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), lambda: np.stack([0 * t_bc, 1 - t_bc, t_bc], -1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), lambda: np.stack([1 - t_ac, 0 * t_ac, t_ac], -1)),
        ((d6 >= 0) & (d5 <= d6), lambda: np.tile([0.0, 0.0, 1.0], (len(p), 1))),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), lambda: np.stack([1 - t_ab, t_ab, 0 * t_ab], -1)),
        ((d3 >= 0) & (d4 <= d3), lambda: np.tile([0.0, 1.0, 0.0], (len(p), 1))),
        ((d1 <= 0) & (d2 <= 0), lambda: np.tile([1.0, 0.0, 0.0], (len(p), 1))),
    ]
    for mask, value in regions:
        if mask.any():
            bary[mask] = value()[mask]
    bary = np.nan_to_num(bary, nan=1.0 / 3.0)  # degenerate triangles
    return np.einsum("nk,nkj->nj", bary, triangles), bary


def surface_truth_at(
    rig: Rig,
    points_rig: ArrayLike,
    *,
    faces: np.ndarray | None = None,
    margin_m: float = 0.002,
    surface: SurfaceTruth | None = None,
    geometry: ObjectGeometry | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The truth albedo at rig-frame surface points, and where it is the plain base.

    Parameters
    ----------
    rig : Rig
        With an ``[object]``; ``rig.simulation.surface`` names the truth unless ``surface``
        is given.
    points_rig : array (N, 3)
        Points on the object's surface in the rig frame (metres).
    faces : array (N,), optional
        The face each point lies on (indices into the mesh as trimesh reads the file), to
        skip the closest-face search.
    margin_m : float
        How far (on the surface) from every patch a point must be to count as uniform.

    Returns
    -------
    albedo : ndarray (N, 3)
        Diffuse albedo per channel (R, G, B): closest face → barycentric → UV → albedo.
    uniform : ndarray (N,) bool
        True where the point has the base albedo and no patch lies within ``margin_m``
        (a lower bound of the surface distance: UV distance times the face's smallest
        UV-to-surface stretch). With no patches, every point is uniform.
    """
    surface = surface or load_surface(rig.simulation.surface)
    geometry = geometry or ObjectGeometry.from_rig(rig)
    points = np.asarray(points_rig, dtype=float).reshape(-1, 3)
    if not surface.varies:
        return surface.albedo_at(None, len(points)), np.ones(len(points), dtype=bool)
    faces, uv = _surface_uv(geometry, points, faces)
    albedo = surface.albedo_at(uv)
    uniform = surface.uv_distance_to_patches(uv) * geometry.uv_metric[faces] >= margin_m
    if surface.maps is not None and surface.maps.albedo is not None:
        uniform[:] = False  # an albedo map promises no plain region
    return albedo, uniform


def surface_finish_at(
    rig: Rig,
    points_rig: ArrayLike,
    *,
    faces: np.ndarray | None = None,
    surface: SurfaceTruth | None = None,
    geometry: ObjectGeometry | None = None,
) -> Finish:
    """The truth finish (GGX α, specular weight, index, metalness) at rig-frame surface points.

    The arguments are those of :func:`surface_truth_at`.
    """
    surface = surface or load_surface(rig.simulation.surface)
    geometry = geometry or ObjectGeometry.from_rig(rig)
    points = np.asarray(points_rig, dtype=float).reshape(-1, 3)
    if not surface.varies:
        return surface.finish_at(None, len(points))
    return surface.finish_at(_surface_uv(geometry, points, faces)[1])


def _surface_uv(
    geometry: ObjectGeometry, points: np.ndarray, faces: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """The face each point lies on and its UV (closest face → barycentric → UV)."""
    if faces is None:
        faces, bary, _ = geometry.closest_faces(points)
    else:
        faces = np.asarray(faces, dtype=np.int64).ravel()
        _, bary = closest_point_on_triangles(geometry.triangles[faces], points)
    uv = geometry.uv_at(faces, bary)
    if uv is None:
        raise ObjectError(f"{geometry.path}: the mesh has no texture coordinates for the surface's patches")
    return faces, uv


# --- generating the shipped files -----------------------------------------------------------------
SHIPPED: dict[str, tuple[Callable[[], trimesh.Trimesh], str]] = {
    "vase.obj": (
        vase_mesh,
        "A vase-like surface of revolution about +y, 5 cm tall, in metres.\n"
        "u = azimuth/2pi (0.5 faces +z), v = height fraction. sim_devices/objects.py:vase_mesh",
    ),
    "relief.obj": (
        relief_plate_mesh,
        "A 6 x 4 cm plate facing +z with Gaussian bumps 2-4 mm high, in metres.\n"
        "u, v along x, y. sim_devices/objects.py:relief_plate_mesh",
    ),
}


def write_shipped(folder: str | Path = OBJECTS_DIR) -> list[Path]:
    """(Re)generate the shipped OBJ files (deterministic)."""
    out = []
    for name, (make, comment) in SHIPPED.items():
        mesh = make()
        header = (
            f"{comment}\nGenerated by python -m sim_devices.objects; {len(mesh.vertices)} vertices, "
            f"{len(mesh.faces)} faces."
        )
        out.append(write_obj(Path(folder) / name, mesh, header))
    return out


if __name__ == "__main__":
    for written in write_shipped():
        print(written)

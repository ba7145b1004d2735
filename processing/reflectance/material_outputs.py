"""The fitted reflectance as files people open: linear OpenEXR maps, PNG previews, and a glTF asset.

Per light model ``brdf-<model>.exr`` holds, in the mesh's UV layout (the camera's view for a
mesh without UVs), the physical values and their 1σ: ``diffuse`` (R, G, B albedo),
``specular`` (R, G, B reflectance at normal incidence, F0), ``roughness`` (GGX α),
``metalness``, ``sigma_diffuse``, ``sigma_specular``, ``sigma_roughness`` and ``confidence``
(2: the point's own lobe, 1: a basis material's, 0: nothing measured), NaN where the camera
saw nothing. PNG previews show the glTF base colour (sRGB) and the confidence.

``object-<model>.glb`` is the mesh (in its own frame, metres) with a glTF 2.0 PBR
metallic-roughness material: the base colour ``(1 − m)·ρ + m·F0`` in sRGB, the
metallic-roughness texture with glTF's roughness ``√α`` in G and the metalness in B, and,
for the dielectric parts, ``KHR_materials_ior`` (1.5) and ``KHR_materials_specular`` whose
colour texture carries F0 / 0.04 (so that F0 = 0.04·colour, glTF's dielectric rule). Texels
the camera never saw take the median of the seen ones, since a texture has no NaN.
Written with trimesh (mesh, textures) and pygltflib (the two extensions), and checked in
the test suite with the Khronos glTF-Validator.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import OpenEXR

from processing.reflectance.brdf import BRDFFit
from processing.reflectance.estimate import ReflectanceResult
from processing.reflectance.maps import splat_uv

#: The layers of ``brdf-<model>.exr``, with their channel counts.
LAYERS = {
    "diffuse": 3,
    "specular": 3,
    "roughness": 1,
    "metalness": 1,
    "sigma_diffuse": 3,
    "sigma_specular": 3,
    "sigma_roughness": 1,
    "confidence": 1,
}
#: F0 of a dielectric of index 1.5: glTF's default, the specular colour's unit.
DIELECTRIC_F0 = 0.04


def fit_layers(fit: BRDFFit) -> dict[str, np.ndarray]:
    """The fit's values per point, one (N, C) array per layer of :data:`LAYERS`."""
    return {
        "diffuse": fit.diffuse,
        "specular": fit.specular,
        "roughness": fit.roughness[:, None],
        "metalness": fit.metalness[:, None],
        "sigma_diffuse": fit.sigma_diffuse,
        "sigma_specular": fit.sigma_specular,
        "sigma_roughness": fit.sigma_roughness[:, None],
        "confidence": fit.confidence[:, None].astype(float),
    }


def layer_maps(fit: BRDFFit, result: ReflectanceResult, texture_size: int) -> dict[str, np.ndarray]:
    """Each layer as an image: in UV space (``texture_size`` square) or on the camera's superpixel grid."""
    layers = fit_layers(fit)
    seen = np.isfinite(fit.roughness)
    maps = {}
    for name, values in layers.items():
        finite = seen & np.all(np.isfinite(values), axis=1)
        if result.uv is not None:
            image = splat_uv(result.uv[finite], values[finite], texture_size)
        else:
            image = np.full((*result.shape, values.shape[1]), np.nan)
            image[result.rows[finite], result.cols[finite]] = values[finite]
        maps[name] = image
    return maps


def write_exr_layers(path: Path, maps: dict[str, np.ndarray]) -> Path:
    """One OpenEXR with a channel per layer (``diffuse.R`` …, ``roughness``), float32, NaN kept."""
    channels = {
        name: np.ascontiguousarray(image if image.shape[-1] == 3 else image[..., 0], dtype=np.float32)
        for name, image in maps.items()
    }
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))
    return path


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] to 8-bit sRGB (IEC 61966-2-1)."""
    x = np.clip(np.nan_to_num(linear, nan=0.0), 0.0, 1.0)
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return (255.0 * encoded + 0.5).astype(np.uint8)


def gltf_textures(maps: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The glTF textures (8-bit RGB) from the layer maps, texels never seen filled with the medians."""

    def filled(image: np.ndarray) -> np.ndarray:
        out = np.array(image, dtype=float)
        for c in range(out.shape[-1]):
            channel = out[..., c]
            finite = np.isfinite(channel)
            channel[~finite] = float(np.median(channel[finite])) if finite.any() else 0.0
        return out

    diffuse, specular = filled(maps["diffuse"]), filled(maps["specular"])
    metal = np.clip(filled(maps["metalness"]), 0.0, 1.0)
    alpha = np.clip(filled(maps["roughness"]), 0.0, 1.0)
    base = (1.0 - metal) * diffuse + metal * specular
    metallic_roughness = np.zeros((*alpha.shape[:2], 3))
    metallic_roughness[..., 1] = np.sqrt(alpha[..., 0])  # glTF's roughness r: α = r²
    metallic_roughness[..., 2] = metal[..., 0]
    specular_colour = np.where(metal > 0.5, 1.0, specular / DIELECTRIC_F0 / 2.0)  # factor 2 below: F0 up to 0.08
    return {
        "base_colour": srgb_encode(base),
        "metallic_roughness": (255.0 * np.clip(metallic_roughness, 0, 1) + 0.5).astype(np.uint8),
        "specular_colour": srgb_encode(np.clip(specular_colour, 0.0, 1.0)),
    }


def write_png(path: Path, rgb: np.ndarray) -> Path:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: could not write the PNG")
    return path


def confidence_png(path: Path, confidence: np.ndarray) -> Path:
    """Green: the texel's own lobe; amber: a basis material's; grey: nothing measured; white: not seen."""
    c = confidence[..., 0]
    rgb = np.full((*c.shape, 3), 255, np.uint8)
    for value, colour in ((2.0, (40, 160, 60)), (1.0, (230, 160, 30)), (0.0, (150, 150, 150))):
        rgb[np.isfinite(c) & (np.round(c) == value)] = colour
    return write_png(path, rgb)


def write_glb(path: Path, mesh: Any, textures: dict[str, np.ndarray], name: str) -> Path:
    """The mesh (object frame, metres, with UVs) and its material as one glTF 2.0 binary."""
    import pygltflib  # noqa: PLC0415 - only where an asset is written
    import trimesh  # noqa: PLC0415
    from PIL import Image  # noqa: PLC0415

    material = trimesh.visual.material.PBRMaterial(
        name=name,
        baseColorTexture=Image.fromarray(textures["base_colour"]),
        metallicRoughnessTexture=Image.fromarray(textures["metallic_roughness"]),
        metallicFactor=1.0,
        roughnessFactor=1.0,
        doubleSided=True,
    )
    uv = np.asarray(mesh.visual.uv, float)
    textured = trimesh.Trimesh(
        mesh.vertices, mesh.faces, visual=trimesh.visual.TextureVisuals(uv=uv, material=material), process=False
    )
    glb = textured.export(file_type="glb")
    gltf = pygltflib.GLTF2.load_from_bytes(glb)
    blob = bytearray(gltf.binary_blob() or b"")
    png = io.BytesIO()
    Image.fromarray(textures["specular_colour"]).save(png, format="PNG")
    data = png.getvalue()
    while len(blob) % 4:
        blob.append(0)
    gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
    blob.extend(data)
    while len(blob) % 4:
        blob.append(0)
    gltf.buffers[0].byteLength = len(blob)
    gltf.images.append(pygltflib.Image(bufferView=len(gltf.bufferViews) - 1, mimeType="image/png"))
    gltf.textures.append(pygltflib.Texture(source=len(gltf.images) - 1, sampler=gltf.textures[0].sampler))
    specular_texture = len(gltf.textures) - 1
    for mat in gltf.materials:
        mat.extensions = {
            **(mat.extensions or {}),
            "KHR_materials_ior": {"ior": 1.5},
            "KHR_materials_specular": {
                "specularFactor": 1.0,
                "specularColorFactor": [2.0, 2.0, 2.0],
                "specularColorTexture": {"index": specular_texture},
            },
        }
    used = set(gltf.extensionsUsed or []) | {"KHR_materials_ior", "KHR_materials_specular"}
    gltf.extensionsUsed = sorted(used)
    gltf.set_binary_blob(bytes(blob))
    path.write_bytes(b"".join(gltf.save_to_bytes()))
    return path


def write_material_outputs(
    materials: Any, result: ReflectanceResult, out: Path, mesh: Any | None, texture_size: int
) -> dict[str, Path]:
    """Per light model the EXR layers, the PNG previews and (for a mesh with UVs) the ``.glb``."""
    files: dict[str, Path] = {}
    for method, fit in materials.fits.items():
        maps = layer_maps(fit, result, texture_size)
        files[f"brdf-{method}.exr"] = write_exr_layers(out / f"brdf-{method}.exr", maps)
        textures = gltf_textures(maps)
        files[f"basecolor-{method}.png"] = write_png(out / f"basecolor-{method}.png", textures["base_colour"])
        files[f"confidence-{method}.png"] = confidence_png(out / f"confidence-{method}.png", maps["confidence"])
        if result.uv is not None and mesh is not None:
            glb = out / f"object-{method}.glb"
            files[glb.name] = write_glb(glb, mesh, textures, f"mirrorgonio {method}")
    return files

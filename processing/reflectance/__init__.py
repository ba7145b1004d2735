"""Diffuse reflectance of an object lit from close by, under three light models.

``docs/measurement.md``, "Diffuse reflectance under near light": an object of
known shape (a mesh registered to the camera) is photographed lit by the measured light
from several positions (the reference experiment: 30 cm away, 10° to 50° in 10° steps).
For a surface point ``r`` with normal ``n`` and observed radiance ``L_o``, a Lambertian
surface has ``ρ = π·L_o / E(r, n)``. The irradiance ``E`` comes from one of three light
models (:data:`LIGHT_MODELS`):

``collimated``
    One direction ``ω₀`` (from the object's centre to the light) and one irradiance
    ``E₀ = I₀/d₀²`` for the whole object: ``E = E₀·max(0, n·ω₀)``.
``isotropic``
    A point of the same intensity ``I₀`` in every direction: ``E = I₀·max(0, n·ω)/d²``.
``measured``
    The fitted near-field model of the light run (:class:`~processing.lightmodel.LightModel`):
    ``E(r, n) = Σ_s I_s(θ_s, φ_s)·max(0, n·ω_s)/|r − p_s|²``.

``I₀ = Σ_s I_s(0)`` is the measured light's total on-axis intensity — what a laboratory
gets from a photometer on the light's axis and the isotropy assumption — and the point the
isotropic and collimated models use is the **intensity-weighted centroid of the sources**
on the light plane (weights ``I_s(0)``), placed in the rig frame by the light's pose.

What one pixel measures (``docs/rig.md``, the simulated camera's radiometry): a pixel's
rate is ``k·⟨L_o·cos⁴β⟩`` with ``k`` the camera's ``sensitivity_e_per_s`` and ``β`` the
chief ray's angle from the optical axis, so ``L_o = rate / (k·cos⁴β)``. The light model is
in the same ``k``-radiometry (its intensities come from the same kind of rates), so ``ρ``
comes out absolute.

The estimate works on superpixels (the 2×2 CFA tiles, :func:`processing.hdr.mosaic.superpixels`):
the chief ray of superpixel ``(i, j)`` leaves the camera centre through the full-resolution
pixel coordinate ``(2j + 0.5, 2i + 0.5)`` (pixel centres at integer coordinates, as in
:mod:`processing.trace`), and meets the mesh (trimesh ray casting, Embree when installed)
at a point with a **flat face normal** turned towards the camera. Each (light, pixel)
sample is then kept or excluded with a code (:data:`SAMPLE_CODES`), each pixel gets a
reason code (:data:`PIXEL_CODES`), and

    ρ_c = π · Σ_j L_jc·E_j / Σ_j E_j²

is the least-squares solution over the usable lights ``j`` — the same samples for all three
methods, so that they are compared on equal points. On an object of uniform albedo the
measured model gives a uniform ρ where the other two show the fall-off towards the object's
top and bottom of the reference paper's Fig. 11 (the near-field light / mirror-ball
goniophotometer paper this project calls "the reference paper").

Entry points: :func:`estimate_reflectance` (arrays in, arrays out) and
:func:`reflectance_from_run` (a run file in, the files of ``docs/reflectance.md`` out).

Modules: :mod:`~processing.reflectance.run` (:func:`reflectance_from_run`),
:mod:`~processing.reflectance.estimate` (:func:`estimate_reflectance`),
:mod:`~processing.reflectance.lights` (the three light models),
:mod:`~processing.reflectance.camera` (the camera's rays on the mesh),
:mod:`~processing.reflectance.codes` (settings and codes), :mod:`~processing.reflectance.maps`
(profiles, texture), :mod:`~processing.reflectance.outputs` (the files) and
:mod:`~processing.reflectance.page` (the report).
"""

from processing.reflectance.codes import METHODS, PIXEL_CODES, SAMPLE_CODES, ReflectanceError, ReflectanceSettings
from processing.reflectance.estimate import ReflectanceResult, estimate_reflectance
from processing.reflectance.lights import (
    LIGHT_MODELS,
    CollimatedLight,
    IsotropicPointLight,
    MeasuredLight,
    light_centre,
)
from processing.reflectance.maps import reflectance_profiles, uv_texture
from processing.reflectance.outputs import write_outputs
from processing.reflectance.run import check_light_frame, find_light_model, load_mesh, reflectance_from_run

__all__ = [
    "LIGHT_MODELS",
    "METHODS",
    "PIXEL_CODES",
    "SAMPLE_CODES",
    "check_light_frame",
    "estimate_reflectance",
    "find_light_model",
    "light_centre",
    "load_mesh",
    "reflectance_from_run",
    "reflectance_profiles",
    "uv_texture",
    "write_outputs",
    "CollimatedLight",
    "IsotropicPointLight",
    "MeasuredLight",
    "ReflectanceError",
    "ReflectanceResult",
    "ReflectanceSettings",
]

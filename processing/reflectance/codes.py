"""The reflectance estimate's vocabulary: its settings, its error, and the codes of samples and pixels."""

from __future__ import annotations

import logging
from dataclasses import dataclass

log = logging.getLogger("mirrorgonio.processing")


METHODS = ("collimated", "isotropic", "measured")


class ReflectanceError(ValueError):
    """Input the reflectance estimate cannot work with (one line naming the file and the cause)."""


# Per (light, pixel) sample; the first that applies, in this order.
SAMPLE_USED = 0


SAMPLE_PIXEL_EXCLUDED = 1


SAMPLE_HOUSING = 2


SAMPLE_GRAZING = 3


SAMPLE_SHADOW = 4


SAMPLE_SATURATED = 5


SAMPLE_NO_IRRADIANCE = 6


SAMPLE_SPECULAR_GEOMETRY = 7


SAMPLE_SPECULAR_OUTLIER = 8


SAMPLE_CODES = {
    SAMPLE_USED: "used",
    SAMPLE_PIXEL_EXCLUDED: "pixel excluded (background, edge or grazing view)",
    SAMPLE_HOUSING: "the light's housing hides the point from the camera",
    SAMPLE_GRAZING: "grazing incidence (or the surface faces away from the light)",
    SAMPLE_SHADOW: "cast shadow (a source is hidden), or within the shadow margin",
    SAMPLE_SATURATED: "saturated in every exposure, or no HDR value",
    SAMPLE_NO_IRRADIANCE: "a light model gives no irradiance (e.g. behind the light plane)",
    SAMPLE_SPECULAR_GEOMETRY: "specular direction: the half vector lies within the specular angle of the normal",
    SAMPLE_SPECULAR_OUTLIER: "specular outlier: radiance far above the other lights' fit",
}


# Per pixel (superpixel).
PIXEL_VALID = 0


PIXEL_BACKGROUND = 1


PIXEL_EDGE = 2


PIXEL_GRAZING_VIEW = 3


PIXEL_FEW_HOUSING = 4


PIXEL_FEW_GRAZING = 5


PIXEL_FEW_SHADOW = 6


PIXEL_FEW_SATURATED = 7


PIXEL_FEW_NO_IRRADIANCE = 8


PIXEL_FEW_SPECULAR = 9


PIXEL_CODES = {
    PIXEL_VALID: "valid",
    PIXEL_BACKGROUND: "background: the chief ray misses the mesh",
    PIXEL_EDGE: "edge: near a silhouette or a depth discontinuity (mixed pixels)",
    PIXEL_GRAZING_VIEW: "grazing view",
    PIXEL_FEW_HOUSING: "too few lights: the light's housing hides the point",
    PIXEL_FEW_GRAZING: "too few lights: grazing incidence",
    PIXEL_FEW_SHADOW: "too few lights: cast shadows",
    PIXEL_FEW_SATURATED: "too few lights: saturated or no HDR value",
    PIXEL_FEW_NO_IRRADIANCE: "too few lights: no irradiance",
    PIXEL_FEW_SPECULAR: "too few lights: specular highlights",
}


PIXEL_SHORT = {
    0: "valid",
    1: "background",
    2: "edge",
    3: "grazing-view",
    4: "few-lights-housing",
    5: "few-lights-grazing",
    6: "few-lights-shadow",
    7: "few-lights-saturated",
    8: "few-lights-no-irradiance",
    9: "few-lights-specular",
}


SAMPLE_SHORT = {
    0: "used",
    1: "pixel-excluded",
    2: "housing",
    3: "grazing",
    4: "shadow",
    5: "saturated",
    6: "no-irradiance",
    7: "specular-geometry",
    8: "specular-outlier",
}


# The reason map's colours (RGB, 0..255).
PIXEL_COLOURS = {
    0: (200, 200, 200),
    1: (0, 0, 0),
    2: (255, 140, 0),
    3: (148, 103, 189),
    4: (140, 86, 75),
    5: (31, 119, 180),
    6: (44, 60, 160),
    7: (214, 39, 40),
    8: (188, 189, 34),
    9: (23, 190, 207),
}


FEW_FROM_SAMPLE = {
    SAMPLE_HOUSING: PIXEL_FEW_HOUSING,
    SAMPLE_GRAZING: PIXEL_FEW_GRAZING,
    SAMPLE_SHADOW: PIXEL_FEW_SHADOW,
    SAMPLE_SATURATED: PIXEL_FEW_SATURATED,
    SAMPLE_NO_IRRADIANCE: PIXEL_FEW_NO_IRRADIANCE,
    SAMPLE_SPECULAR_GEOMETRY: PIXEL_FEW_SPECULAR,
    SAMPLE_SPECULAR_OUTLIER: PIXEL_FEW_SPECULAR,
}


@dataclass(frozen=True)
class ReflectanceSettings:
    """The thresholds of the sample selection (``docs/reflectance.md``).

    Attributes
    ----------
    grazing_light_deg : float
        A sample is excluded when the light (its isotropic point) stands less than this
        elevation above the face's plane (``n·ω < sin``).
    grazing_view_deg : float
        A pixel is excluded when the camera sees its face at less than this elevation.
    specular_deg : float
        A sample is excluded when the half vector of the light and view directions lies
        within this angle of the normal (where a specular lobe would peak). 0 disables it.
    outlier : float
        Residual test: with at least 3 usable lights, the light whose radiance exceeds the
        prediction of the other lights' fit by more than this fraction is dropped, one
        light at a time. ``inf`` disables it.
    edge_margin : int
        Superpixels by which silhouettes and depth discontinuities are dilated.
    shadow_margin : int
        Superpixels by which each light's cast shadow is dilated (penumbra, camera blur).
    depth_tolerance : float
        A depth jump between neighbouring pixels larger than this many superpixel
        footprints, that neither pixel's face plane explains, is a discontinuity.
    min_lights : int
        Usable lights a pixel needs (at least 2).
    """

    grazing_light_deg: float = 15.0
    grazing_view_deg: float = 15.0
    specular_deg: float = 15.0
    outlier: float = 0.05
    edge_margin: int = 2
    shadow_margin: int = 1
    depth_tolerance: float = 3.0
    min_lights: int = 2

    def __post_init__(self) -> None:
        for name in ("grazing_light_deg", "grazing_view_deg", "specular_deg"):
            value = getattr(self, name)
            if not (0.0 <= value < 90.0):
                raise ReflectanceError(f"{name}: must be in [0, 90) degrees, got {value}")
        if not self.outlier > 0:
            raise ReflectanceError(f"outlier: must be a positive fraction, got {self.outlier}")
        for name in ("edge_margin", "shadow_margin"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 0:
                raise ReflectanceError(f"{name}: must be a whole number >= 0, got {getattr(self, name)}")
        if not self.depth_tolerance > 0:
            raise ReflectanceError(f"depth_tolerance: must be positive, got {self.depth_tolerance}")
        if int(self.min_lights) != self.min_lights or self.min_lights < 2:
            raise ReflectanceError(f"min_lights: must be a whole number >= 2, got {self.min_lights}")

"""The reflectance estimate's vocabulary: its settings, its error, and the codes of samples and pixels."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import ClassVar

from processing.options import ReflectanceThresholds

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
class ReflectanceSettings(ReflectanceThresholds):
    """The thresholds of the sample selection (``docs/reflectance.md``): each one
    :class:`~processing.options.Option`, declared in :class:`processing.options.ReflectanceThresholds`
    (light, for the command line); a value out of its bounds is a :class:`ReflectanceError`.

    Examples
    --------
    >>> ReflectanceSettings(outlier=0.0)
    Traceback (most recent call last):
    ...
    processing.reflectance.codes.ReflectanceError: --outlier: expected a positive number, got 0.0
    """

    error: ClassVar[type[ValueError]] = ReflectanceError

"""The camera's photometric calibration as the rig file keeps it (``[camera.photometric]``)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, PositiveFloat

from drivers.config_files import ConfigModel

RGB = tuple[float, float, float]


class PhotometricCalibration(ConfigModel):
    """The camera's photometric scale, measured against a reference (``mirrorgonio
    calibrate-photometry``): with it the light model, the report and the light files are in
    candela and lumens.

    ``candela_per_unit`` is the luminous intensity, in candela, of one unit of the light
    model's intensity (the camera channels' mean) for a light of the reference's colour
    (``reference_camera_rgb``, channel mean 1); a light of another colour is scaled by its
    luminance over the reference's through the camera's colour matrices. The model's unit is
    the camera's signal over ``gain_e_per_dn / sensitivity_e_per_s`` as described when the
    calibration was made: a description that changes them rescales the calibration, the
    physical camera being the same. ``relative_uncertainty`` is its 1σ as a fraction.
    """

    candela_per_unit: PositiveFloat
    relative_uncertainty: Annotated[float, Field(ge=0.0, lt=1.0)]
    reference_camera_rgb: RGB | None = None
    gain_e_per_dn: PositiveFloat
    sensitivity_e_per_s: PositiveFloat
    reference: str = Field(min_length=1, max_length=500)
    run_id: str | None = None
    made_utc: str | None = None

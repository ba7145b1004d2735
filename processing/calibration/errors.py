"""The calibration's one error: an image or a fit that cannot give the ball's position."""

from __future__ import annotations


class CalibrationError(ValueError):
    """A calibration image or fit that cannot give the ball's position (one line)."""

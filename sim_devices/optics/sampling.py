"""Sample patterns: stratified points over the unit disc (an aperture, an ellipse) and over a pixel."""

from __future__ import annotations

import math

import numpy as np

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def unit_disc_samples(count: int, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Stratified points over the unit disc, a fresh random shift for every set.

    Vogel's sunflower spiral (equal-area radial strata, golden-angle azimuths), with the
    position inside each radial stratum and the spiral's rotation drawn at random per
    set. Without the radial shift the fraction of points inside a centred circle is
    fixed by the pattern and biases small pre-images (e.g. 21 of 48 points for an area
    fraction of 0.444).

    Returns
    -------
    ndarray, shape (*shape, count, 2)
    """
    j = np.arange(count)
    shift = rng.random((*shape, 1))
    spin = rng.random((*shape, 1)) * 2.0 * math.pi
    r = np.sqrt((j + shift) / count)
    a = j * GOLDEN_ANGLE + spin
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=-1)


def subpixel_pattern(per_side: int) -> np.ndarray:
    """Stratum corners of a ``per_side``² grid over the pixel (jitter is added per pixel)."""
    g = (np.arange(per_side) / per_side) - 0.5
    xs, ys = np.meshgrid(g, g)
    return np.column_stack([xs.ravel(), ys.ravel()])

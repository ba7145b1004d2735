"""A correction to the templates' point spread: kernels added to each channel's computed (or
measured) pattern, as :mod:`processing.unmixing.point_spread_fit` estimates them from a sweep."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class PointSpreadCorrection:
    """``kernels`` (3, 2R+1, 2R+1): what each channel's kernel gains (a fraction of the point's
    flux per pixel, the chief ray's pixel in the middle). Hashed and compared on the content,
    as :class:`~processing.unmixing.measured.MeasuredKernels`, so that cached templates hold."""

    kernels: np.ndarray
    digest: str

    @classmethod
    def of(cls, kernels: np.ndarray) -> PointSpreadCorrection:
        array = np.array(kernels, dtype=float)
        array.flags.writeable = False
        return cls(array, hashlib.sha256(array.tobytes()).hexdigest())

    def __hash__(self) -> int:
        return hash(self.digest)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, PointSpreadCorrection) and other.digest == self.digest

    @property
    def reach(self) -> int:
        return self.kernels.shape[1] // 2

    def added_to(self, kernels: list[np.ndarray]) -> list[np.ndarray]:
        """Each channel's ``kernels`` (square, odd, centred) plus the correction on their grid:
        cropped to it where the correction reaches farther (the template's reach stays the one
        the builder chose), padded where it reaches less.

        Examples
        --------
        >>> correction = PointSpreadCorrection.of(np.full((3, 3, 3), 0.1))
        >>> correction.added_to([np.ones((1, 1))] * 3)[0].tolist()  # cropped to the kernel's one pixel
        [[1.1]]
        >>> correction.added_to([np.zeros((5, 5))] * 3)[0][1:4, 1:4].tolist() == np.full((3, 3), 0.1).tolist()
        True
        """
        out = []
        for kernel, extra in zip(kernels, self.kernels, strict=True):
            half, k = kernel.shape[0] // 2, extra.shape[0] // 2
            keep = min(half, k)
            total = np.array(kernel, dtype=float)
            total[half - keep : half + keep + 1, half - keep : half + keep + 1] += extra[
                k - keep : k + keep + 1, k - keep : k + keep + 1
            ]
            out.append(total)
        return out

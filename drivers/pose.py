"""Rigid poses of the arm's tool and of the light.

A pose is a position in metres and an orientation given as fixed-axis X-Y-Z angles in
radians (``R = Rz(rz) @ Ry(ry) @ Rx(rx)``): the A, B, C convention of robot controllers
such as Mitsubishi's MELFA, so a pose can be sent to an arm without conversion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


def rotation_from_angles(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation matrix ``Rz(rz) @ Ry(ry) @ Rx(rx)`` (angles in radians).

    Examples
    --------
    A quarter turn about z takes x to y:

    >>> (rotation_from_angles(0.0, 0.0, math.pi / 2) @ [1.0, 0.0, 0.0]).round(12).tolist()
    [0.0, 1.0, 0.0]
    """
    cx, sx = math.cos(rx), math.sin(rx)
    cy, sy = math.cos(ry), math.sin(ry)
    cz, sz = math.cos(rz), math.sin(rz)
    return np.array(
        [
            [cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
            [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
            [-sy, cy * sx, cy * cx],
        ]
    )


def angles_from_rotation(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_angles`; ``ry`` in [-pi/2, pi/2]."""
    r = np.asarray(rotation, dtype=float)
    ry = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        rx = math.atan2(r[2, 1], r[2, 2])
        rz = math.atan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: rx and rz share one degree of freedom, put it all in rx
        rz = 0.0
        rx = math.atan2(-r[1, 2], r[1, 1])
    return rx, ry, rz


@dataclass(frozen=True)
class Pose:
    """Position (m) and fixed-axis X-Y-Z orientation (rad) of a frame in the rig frame."""

    x: float
    y: float
    z: float
    rx: float = 0.0
    ry: float = 0.0
    rz: float = 0.0

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    @property
    def rotation(self) -> np.ndarray:
        """Columns are the frame's x, y, z axes expressed in the rig frame."""
        return rotation_from_angles(self.rx, self.ry, self.rz)

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform from this frame to the rig frame."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.position
        return m

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Pose:
        m = np.asarray(matrix, dtype=float)
        rx, ry, rz = angles_from_rotation(m[:3, :3])
        return cls(float(m[0, 3]), float(m[1, 3]), float(m[2, 3]), rx, ry, rz)

    @classmethod
    def from_rotation(cls, position: ArrayLike, rotation: np.ndarray) -> Pose:
        rx, ry, rz = angles_from_rotation(rotation)
        p = np.asarray(position, dtype=float)
        return cls(float(p[0]), float(p[1]), float(p[2]), rx, ry, rz)

    def compose(self, other: Pose) -> Pose:
        """``self ∘ other``: ``other`` is expressed in this pose's frame."""
        return Pose.from_matrix(self.matrix() @ other.matrix())

    def inverse(self) -> Pose:
        return Pose.from_matrix(np.linalg.inv(self.matrix()))

    def as_tuple(self) -> tuple[float, float, float, float, float, float]:
        return (self.x, self.y, self.z, self.rx, self.ry, self.rz)

    def distance_to(self, other: Pose) -> tuple[float, float]:
        """Translation distance (m) and rotation angle (rad) between two poses."""
        dp = float(np.linalg.norm(self.position - other.position))
        relative = self.rotation.T @ other.rotation
        cos_angle = (np.trace(relative) - 1.0) / 2.0
        return dp, math.acos(max(-1.0, min(1.0, cos_angle)))


AXES = ("x", "y", "z", "rx", "ry", "rz")

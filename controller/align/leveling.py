"""Leveling with the A/B table, the second-face angle, and the CAD model rotated to match.

Pure functions (Padathu 2005; docs/contract.md §4). Angles in degrees.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from controller.motion.kinematics import Trunnion, homogeneous, rotation_matrix, unit

F = NDArray[np.float64]
Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Leveling:
    a_deg: float                 # A table angle
    second_deg: float            # B (AB table) or C (AC table) angle
    rotation: F                  # 3×3 the table applies: rotation @ normal = +Z
    tilt_deg: float              # angle between the normal and +Z before leveling

    @property
    def b_deg(self) -> float:
        return self.second_deg


def leveling_angles(normal: ArrayLike, table: Trunnion | None = None) -> Leveling:
    """The unique table angles (smallest rotation within the limits) that bring `normal` to +Z.

    Default table: the cell.yaml default, A about x (inner, applied first), B about y (outer).
    With A about x and B about y the closed form is ``A = atan2(n_y, n_z)``,
    ``B = atan2(-n_x, sqrt(n_y² + n_z²))``.
    """
    t = table or Trunnion()
    n = unit(normal)
    a, s = t.orient(n, Z)
    rot = t.matrix(a, s)[:3, :3]
    return Leveling(a_deg=a, second_deg=s, rotation=rot,
                    tilt_deg=float(np.degrees(np.arccos(np.clip(n @ Z, -1.0, 1.0)))))


@dataclass(frozen=True)
class FaceAngle:
    angle_deg: float             # Padathu eq. 1: cos θ = n1·n2 / (|n1||n2|), in [0°, 180°]
    signed_deg: float            # rotation about `about` that turns the CAD face normal onto the fitted one
    cad_rotation: F              # 4×4 that rotates the CAD model about `about` through `pivot` to match
    residual_deg: float          # eq. 1 again after rotating the CAD normal (the paper's check)


def face_angle(fitted_normal: ArrayLike, cad_normal: ArrayLike, *, about: ArrayLike = Z,
               pivot: ArrayLike = (0.0, 0.0, 0.0)) -> FaceAngle:
    """Angle between a fitted face and its CAD face, and the CAD rotation that matches them.

    After leveling the top face the part must not move again, so the CAD model is rotated
    about the table's vertical axis (`about`) by the signed angle between the two normals
    projected on the plane normal to it.
    """
    n1, n2, ax = unit(fitted_normal), unit(cad_normal), unit(about)
    theta = float(np.degrees(np.arccos(np.clip(n1 @ n2, -1.0, 1.0))))
    p1 = n1 - ax * (n1 @ ax)
    p2 = n2 - ax * (n2 @ ax)
    signed = float(np.degrees(np.arctan2(ax @ np.cross(p2, p1), p2 @ p1)))
    r = rotation_matrix(ax, signed)
    c = np.asarray(pivot, dtype=float)
    m = homogeneous(r, c - r @ c)
    after = r @ n2
    resid = float(np.degrees(np.arccos(np.clip(unit(p1) @ unit(after - ax * (after @ ax)), -1.0, 1.0))))
    return FaceAngle(angle_deg=theta, signed_deg=signed, cad_rotation=m, residual_deg=resid)


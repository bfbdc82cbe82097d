"""The CNC simulator's own trunnion-table forward kinematics (docs/kinematics.md).

Written independently of controller/motion/kinematics.py (the simulator must not trust the
controller's math): inner axis applied first, outer carries it; AB: A inner, B outer; AC: C
inner, A outer; outer axis through −P, inner axis through −P + offset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from core.config import Kinematics


def rot(axis: ArrayLike, deg: float) -> np.ndarray:
    """4x4 right-handed rotation by `deg` about the unit vector `axis` (Rodrigues), in plain floats:
    the executor asks for two per stretch of motion, about a millisecond apart at time scale 10."""
    x, y, z = (float(v) for v in np.asarray(axis, dtype=float).reshape(3))
    n = math.sqrt(x * x + y * y + z * z)
    x, y, z = x / n, y / n, z / n
    t = math.radians(deg)
    s, c = math.sin(t), math.cos(t)
    v = 1.0 - c
    return np.array([[c + x * x * v, x * y * v - z * s, x * z * v + y * s, 0.0],
                     [y * x * v + z * s, c + y * y * v, y * z * v - x * s, 0.0],
                     [z * x * v - y * s, z * y * v + x * s, c + z * z * v, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])


def trans(v: ArrayLike) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = v
    return m


@dataclass(frozen=True)
class TableKin:
    """A/B or A/C trunnion: table (part-on-table) frame → machine frame at the rotary positions."""

    table: str = "AB"
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis_a: tuple[float, float, float] = (1.0, 0.0, 0.0)
    axis_second: tuple[float, float, float] = (0.0, 1.0, 0.0)
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_config(cls, kin: Kinematics) -> "TableKin":
        return cls(str(kin.table), kin.pivot_mm, kin.axis_a, kin.axis_second, kin.offset_mm)

    @property
    def letters(self) -> str:
        """The G-code axis letters of this machine: XYZAB or XYZAC."""
        return "XYZA" + self.table[1]

    def matrix(self, a_deg: float, second_deg: float) -> np.ndarray:
        c2 = -np.asarray(self.pivot, dtype=float)
        c1 = c2 + np.asarray(self.offset, dtype=float)
        if self.table == "AC":
            inner, outer = rot(self.axis_second, second_deg), rot(self.axis_a, a_deg)
        else:
            inner, outer = rot(self.axis_a, a_deg), rot(self.axis_second, second_deg)
        # T(c2) O T(-c2) T(c1) I T(-c1) with the translations folded in: x -> O (I (x - c1) + c1 - c2) + c2
        o, i = outer[:3, :3], inner[:3, :3]
        m = np.eye(4)
        m[:3, :3] = o @ i
        m[:3, 3] = o @ (c1 - c2 - i @ c1) + c2
        return m

    def tool_in_table(self, a_deg: float, second_deg: float) -> np.ndarray:
        """The fixed tool axis (machine +Z) seen in the table frame."""
        axis: np.ndarray = self.matrix(a_deg, second_deg)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        return axis

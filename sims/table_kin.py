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
    """4x4 right-handed rotation by `deg` about the unit vector `axis` (Rodrigues)."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    t = math.radians(deg)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(t) * kx + (1 - math.cos(t)) * (kx @ kx)
    return m


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
        m: np.ndarray = trans(c2) @ outer @ trans(-c2) @ trans(c1) @ inner @ trans(-c1)
        return m

    def tool_in_table(self, a_deg: float, second_deg: float) -> np.ndarray:
        """The fixed tool axis (machine +Z) seen in the table frame."""
        axis: np.ndarray = self.matrix(a_deg, second_deg)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        return axis

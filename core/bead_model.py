"""Scalar bead geometry shared by the planner's process model and the simulated world (pure).

- `ribeiro_forward`: Ribeiro 1997's forward model `w = K1·I^K2·S^K3`, `h = K4·I^K5·S^K6` (I in A,
  S in mm/min, mm), the same formula as planner.process.forward, for one point (no numpy arrays,
  no envelope check): the simulators may import core only.
- `wire_area_mm2`: the metal a bead lays per mm of travel, `π·D²/4 · WFS / S` (Ding 2015's λ).
- `parabola_peak_mm`: the peak of Ding's parabola profile of a width and a cross-section area
  (area = 2/3 · w · h).
"""
from __future__ import annotations

import math

from core.material import RibeiroCoefficients

__all__ = ["ribeiro_forward", "wire_area_mm2", "parabola_peak_mm"]


def ribeiro_forward(k: RibeiroCoefficients, current_a: float, speed_mm_min: float) -> tuple[float, float]:
    """Bead (width_mm, height_mm) at a current (A) and travel speed (mm/min); both must be positive."""
    if current_a <= 0.0 or speed_mm_min <= 0.0:
        raise ValueError(f"the bead model needs a positive current and speed (got {current_a} A, {speed_mm_min} mm/min)")
    w = k.k1 * current_a ** k.k2 * speed_mm_min ** k.k3
    h = k.k4 * current_a ** k.k5 * speed_mm_min ** k.k6
    return w, h


def wire_area_mm2(wire_diameter_mm: float, wfs_m_min: float, speed_mm_min: float) -> float:
    """Cross-section (mm²) of the wire metal laid per mm of travel: π·D²/4 · WFS / S."""
    if speed_mm_min <= 0.0:
        raise ValueError(f"the travel speed must be positive (got {speed_mm_min} mm/min)")
    return math.pi * wire_diameter_mm ** 2 / 4.0 * max(wfs_m_min, 0.0) * 1000.0 / speed_mm_min


def parabola_peak_mm(width_mm: float, area_mm2: float) -> float:
    """Peak height of Ding's parabola `y = h·(1 − (2x/w)²)` holding that area (2/3·w·h)."""
    return 1.5 * area_mm2 / width_mm

"""Mass balance (DESIGN.md §3.7): the wire a pass lays equals the cross-section it fills.

Laid: A = π·D²/4 · WFS / v (Ding 2015's wire volume per length). Filled: the bead's share of
the layer (step-over × layer height for overlapped beads) or its profile area when it is alone.
The welding point keeps its current and wire feed (so the arc stays on the synergic line); the
travel speed is solved for the balance.
"""
from __future__ import annotations

import math


def laid_area_mm2(wire_diameter_mm: float, wfs_m_min: float, speed_mm_min: float) -> float:
    """Cross-section of metal a pass lays per mm of travel."""
    return math.pi * wire_diameter_mm ** 2 / 4.0 * wfs_m_min * 1000.0 / speed_mm_min


def balanced_speed(wire_diameter_mm: float, wfs_m_min: float, filled_mm2: float) -> float:
    """Travel speed (mm/min) at which the pass lays exactly `filled_mm2` per mm."""
    return math.pi * wire_diameter_mm ** 2 / 4.0 * wfs_m_min * 1000.0 / filled_mm2


def balance_error(wire_diameter_mm: float, wfs_m_min: float, speed_mm_min: float, filled_mm2: float) -> float:
    """|laid − filled| / filled for the numbers as written in the job."""
    return abs(laid_area_mm2(wire_diameter_mm, wfs_m_min, speed_mm_min) - filled_mm2) / filled_mm2

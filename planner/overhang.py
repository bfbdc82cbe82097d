"""The overhang rule of Kerschbaumer 2004, per layer: a pure function a 3- or 5-axis plan can call.

A bead steps out over the layer below by Δx; with the wall leaning α from the horizontal,
Δx = Δz / tan α. A 3-axis path builds it while Δx ≤ Δz·tan(max lean from vertical) and never
beyond half a bead (w/2: the process becomes unstable). A 5-axis plan that tilts the torch by
`tilt_deg` toward the overhang adds that tilt to the lean it may build.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely


@dataclass(frozen=True)
class OverhangCheck:
    """One layer against the layer below: the worst step out and what it leaves unsupported."""

    step_out_mm: float  # largest distance of the layer's contour from the layer below
    limit_mm: float  # largest step out the rule allows
    unsupported_mm2: float  # layer area beyond the limit
    where: tuple[float, float] | None  # a point of the unsupported area (for the message)

    @property
    def ok(self) -> bool:
        return self.where is None


def overhang_limit_mm(dz_mm: float, width_mm: float, max_overhang_deg: float, tilt_deg: float = 0.0) -> float:
    """Largest step out per layer: Δz·tan(max lean + tilt), capped at w/2 (Kerschbaumer)."""
    lean = min(max_overhang_deg + tilt_deg, 89.0)
    cap = 0.5 * width_mm if tilt_deg <= 0 else math.inf  # a tilted torch builds on the wall's side
    return min(dz_mm * math.tan(math.radians(lean)), cap)


def check_overhang(below: shapely.Geometry | None, layer: shapely.Geometry, dz_mm: float, width_mm: float, max_overhang_deg: float,
                   tilt_deg: float = 0.0) -> OverhangCheck:
    """`layer` (a shapely region) against `below` (None: it rests on the substrate)."""
    limit = overhang_limit_mm(dz_mm, width_mm, max_overhang_deg, tilt_deg)
    if below is None or layer.is_empty:
        return OverhangCheck(0.0, limit, 0.0, None)
    if below.is_empty:
        c = layer.representative_point()
        return OverhangCheck(math.inf, limit, float(layer.area), (c.x, c.y))
    pts = shapely.points(shapely.get_coordinates(layer.boundary))
    step = float(np.max(shapely.distance(pts, below))) if len(pts) else 0.0
    if step <= limit:
        return OverhangCheck(step, limit, 0.0, None)
    # Faceting: slivers narrower than 1 % of a bead (or smaller than 0.05 w²) are not overhangs.
    rest = layer.difference(below.buffer(limit, quad_segs=8)).buffer(-0.005 * width_mm).buffer(0.005 * width_mm)
    if rest.is_empty or rest.area < 0.05 * width_mm * width_mm:
        return OverhangCheck(step, limit, 0.0, None)
    c = rest.representative_point()
    return OverhangCheck(step, limit, float(rest.area), (c.x, c.y))

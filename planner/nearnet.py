"""Near-net planning (DESIGN.md §3.9): the part built oversize by a machining allowance, then machined.

* Every layer's islands grow outward by the allowance `a` (round offsets: a distance from the
  surface), holes shrink by it; the part's top grows by `a` too: layers repeating the top
  layer's grown region are added until the deposit stands at least `a` above the net top. The
  bottom stands on the substrate and is not grown (it is cut off the plate).
* Coverage, outside and mass balance are then judged against the grown region.
* Stock left to machine per face: on the sides, the distance from the net contour out to the
  edge of the beads' footprint (min and max over the layers; negative where the beads do not
  reach the net surface), on the top the deposit's height over the net top, at the bottom 0.
* A thin feature refused at the net size names the allowance that would make it buildable
  (`allowance_for`).

Pure: no I/O, no clocks.
"""
from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon

from planner.regions import polygons_of
from planner.thin import Widths, layout

STEP_MM = 0.05  # resolution of the allowance a refused feature is told it needs


def grow(polys: list[Polygon], allowance_mm: float) -> list[Polygon]:
    """The islands grown outward by the allowance (islands closer than 2a merge)."""
    if allowance_mm <= 0.0 or not polys:
        return polys
    grown = shapely.union_all(shapely.buffer(np.asarray(polys, dtype=object), allowance_mm, quad_segs=8))
    return [p for p in polygons_of(grown) if p.area > 1e-9]


def layer_count(height_mm: float, layer_mm: float, allowance_mm: float, net_layers: int) -> int:
    """Layers of the near-net deposit: the net ones, and enough more for the top to stand `a` over it."""
    if allowance_mm <= 0.0:
        return net_layers
    return max(net_layers, int(math.ceil((height_mm + allowance_mm) / layer_mm - 1e-9)))


def fits(W: float, wd: Widths) -> bool:
    """Whether a thin feature W wide gets a legal bead layout (the verdict's own test)."""
    lay = layout(W, wd)
    if lay is None:
        return False
    if lay.n == 1:
        return W <= wd.hi / 0.97
    return lay.filled >= 0.97 * W


def allowance_for(W: float, wd: Widths, limit_mm: float) -> float | None:
    """The smallest allowance (a multiple of 0.05 mm, at most `limit_mm`) that makes a feature W
    wide buildable, or None."""
    for k in range(int(limit_mm / STEP_MM) + 1):
        a = k * STEP_MM
        if fits(W + 2.0 * a, wd):
            return round(a, 2)
    return None


def side_stock(net: shapely.Geometry, footprint: shapely.Geometry, width: float) -> tuple[float, float] | None:
    """(min, max) distance from the net contour out to the beads' edge; negative: the beads stop short."""
    if net.is_empty or footprint.is_empty:
        return None
    pts = shapely.get_coordinates(shapely.segmentize(net.boundary, 0.5 * width))
    if len(pts) == 0:
        return None
    d = shapely.distance(shapely.points(pts), footprint.boundary)
    inside = shapely.contains_xy(footprint, pts[:, 0], pts[:, 1])
    sd = np.where(inside, d, -d)
    return float(sd.min()), float(sd.max())

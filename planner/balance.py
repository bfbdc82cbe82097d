"""Mass balance (DESIGN.md §3.7): the wire a pass lays equals the cross-section it fills.

Laid: A = π·D²/4 · WFS / v (Ding 2015's wire volume per length). Filled: the bead's share of
the layer (step-over × layer height for overlapped beads) or its profile area when it is alone.
The welding point keeps its current and wire feed (so the arc stays on the synergic line); the
travel speed is solved for the balance.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import shapely
from shapely.geometry import Polygon

from planner.path2d import Path2D


def laid_area_mm2(wire_diameter_mm: float, wfs_m_min: float, speed_mm_min: float) -> float:
    """Cross-section of metal a pass lays per mm of travel."""
    return math.pi * wire_diameter_mm ** 2 / 4.0 * wfs_m_min * 1000.0 / speed_mm_min


def balanced_speed(wire_diameter_mm: float, wfs_m_min: float, filled_mm2: float) -> float:
    """Travel speed (mm/min) at which the pass lays exactly `filled_mm2` per mm."""
    return math.pi * wire_diameter_mm ** 2 / 4.0 * wfs_m_min * 1000.0 / filled_mm2


def balance_error(wire_diameter_mm: float, wfs_m_min: float, speed_mm_min: float, filled_mm2: float) -> float:
    """|laid − filled| / filled for the numbers as written in the job."""
    return abs(laid_area_mm2(wire_diameter_mm, wfs_m_min, speed_mm_min) - filled_mm2) / filled_mm2


MAX_SAMPLES = 20_000  # sample points per island: the partition's cost is bounded on large layers


def partition_shares(island: Polygon, beads: Sequence[Path2D], width: float) -> np.ndarray:
    """The width of the strip each bead fills (mm): the island's area nearest to its centre line
    divided by its length (DESIGN.md §3.7, docs/planner.md "Mass balance").

    The island is split among its beads by nearest centre line (a Voronoi partition of the bead
    paths, sampled on a grid about w/5 apart), so the shares add up to the island's area exactly:
    a lone bead fills its wall's whole section, an outermost loop the half step-over plus the
    edge, a pocket bead the pocket. Deterministic (a fixed grid, ties to the lower index).
    """
    n = len(beads)
    lengths = np.array([b.length for b in beads])
    area = float(island.area)
    if n == 0 or area <= 0.0:
        return np.zeros(n)
    minx, miny, maxx, maxy = island.bounds
    g = max(width / 5.0, float(np.sqrt(area / MAX_SAMPLES)))
    xs = np.arange(minx + 0.5 * g, maxx, g)
    ys = np.arange(miny + 0.5 * g, maxy, g)
    gx, gy = np.meshgrid(xs, ys)
    px, py = gx.ravel(), gy.ravel()
    inside = shapely.contains_xy(island, px, py)
    if not inside.any():  # smaller than the grid: shared by length
        return np.full(n, area / max(float(lengths.sum()), 1e-9))
    pts = shapely.points(np.column_stack([px[inside], py[inside]]))
    lines = np.array([shapely.linestrings(b.points) for b in beads], dtype=object)
    hit = shapely.STRtree(lines).query_nearest(pts, all_matches=False)
    counts = np.bincount(hit[1], minlength=n).astype(np.float64)
    near = counts / counts.sum() * area
    return near / np.maximum(lengths, 1e-9)

"""Ding 2015's stability check: the share of bead length whose centre line has another bead's
centre line closer than the material's stable limit (min_step_over_ratio × its width)."""
from __future__ import annotations

import numpy as np
import shapely

from planner.path2d import Path2D


def close_share(paths: list[Path2D], ratio: float, width: float) -> float:
    """Share of sampled bead length (every w/2) with a neighbour closer than ratio × its width.

    Where beads meet end to end (a scan row reaching a loop, a link) the distance falls below
    w/4: that is a junction, not a pair of overlapping neighbours, and is not counted.
    """
    if len(paths) < 2:
        return 0.0
    lines = np.array([shapely.linestrings(p.points) for p in paths], dtype=object)
    lengths = shapely.length(lines)
    n = np.maximum(1, np.floor(lengths / (0.5 * width)).astype(int))
    owner = np.repeat(np.arange(len(paths)), n)
    frac = np.concatenate([(np.arange(k) + 0.5) / k for k in n])
    pts = shapely.line_interpolate_point(lines[owner], frac, normalized=True)
    limit = ratio * np.array([p.width_mm for p in paths])[owner]
    tree = shapely.STRtree(lines)
    si, li = tree.query(pts, predicate="dwithin", distance=float(limit.max()))
    other = owner[si] != li
    si, li = si[other], li[other]
    if len(si) == 0:
        return 0.0
    d = shapely.distance(pts[si], lines[li])
    close = (d < 0.98 * limit[si]) & (d > 0.25 * width)
    return float(len(np.unique(si[close])) / len(pts))

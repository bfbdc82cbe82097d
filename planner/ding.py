"""Ding 2015's stability check: the share of bead length whose centre line has another bead's
centre line closer than the material's stable limit (min_step_over_ratio × its width)."""
from __future__ import annotations

import numpy as np
import shapely

from planner.path2d import Path2D

PIECE = 8  # segments per piece of centre line the search indexes (docs/plan-speed.md)


def close_share(paths: list[Path2D], ratio: float, width: float) -> float:
    """Share of sampled bead length (every w/2) with a neighbour closer than ratio × its width.

    Where beads meet end to end (a scan row reaching a loop, a link) the distance falls below
    w/4: that is a junction, not a pair of overlapping neighbours, and is not counted.

    The search indexes pieces of `PIECE` segments, not whole beads: a zigzag's box covers its
    whole region, so every sample would measure its distance to every row of it. A sample's
    distance to a bead is the least of its distances to the bead's pieces (GEOS measures a line
    segment by segment: the same number).
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
    pieces, piece_of = _pieces(paths)
    tree = shapely.STRtree(pieces)
    si, ki = tree.query(pts, predicate="dwithin", distance=float(limit.max()))
    li = piece_of[ki]
    other = owner[si] != li
    si, ki, li = si[other], ki[other], li[other]
    if len(si) == 0:
        return 0.0
    d = shapely.distance(pts[si], pieces[ki])
    # the least distance per (sample, bead): pairs sorted by sample, bead, distance; the first of each kept
    order = np.lexsort((d, li, si))
    si, li, d = si[order], li[order], d[order]
    first = np.r_[True, (si[1:] != si[:-1]) | (li[1:] != li[:-1])]
    si, d = si[first], d[first]
    close = (d < 0.98 * limit[si]) & (d > 0.25 * width)
    return float(len(np.unique(si[close])) / len(pts))


def _pieces(paths: list[Path2D]) -> tuple[np.ndarray, np.ndarray]:
    """Every centre line cut into runs of at most `PIECE` segments (neighbouring runs share a
    point), and the bead each run belongs to."""
    pts = np.concatenate([p.points[:, :2] for p in paths])
    npts = np.array([len(p.points) for p in paths])
    segs = np.maximum(npts - 1, 1)
    per = -(-segs // PIECE)                                   # runs of each bead
    bead = np.repeat(np.arange(len(paths)), per)
    k = np.arange(len(bead)) - np.repeat(np.cumsum(per) - per, per)   # the run's rank in its bead
    start = np.repeat(np.cumsum(npts) - npts, per) + k * PIECE
    count = np.minimum(PIECE, segs[bead] - k * PIECE) + 1
    run = np.repeat(np.arange(len(bead)), count)
    at = np.repeat(start - (np.cumsum(count) - count), count) + np.arange(int(count.sum()))
    return shapely.linestrings(pts[at], indices=run), bead

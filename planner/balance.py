"""Mass balance (docs/contract.md §3.7): the wire a pass lays equals the cross-section it fills.

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
import shapely.errors
from shapely.geometry import Polygon

from planner.cellclip import cell_areas_inside
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


def partition_shares(island: Polygon, beads: Sequence[Path2D], width: float) -> np.ndarray:
    """The width of the strip each bead fills (mm): the island's area nearest to its centre line
    divided by its length (docs/contract.md §3.7, docs/planner.md "Mass balance").

    The island is split among its beads by nearest centre line: the Voronoi diagram of points
    every w/8 along the beads, cells gathered by bead and clipped to the island. The shares add
    up to the island's area exactly: a lone bead fills its wall's whole section, an outermost
    loop the half step-over plus the edge, a pocket bead its pocket. Deterministic.
    """
    n = len(beads)
    lengths = np.array([b.length for b in beads])
    area = float(island.area)
    if n == 0 or area <= 0.0:
        return np.zeros(n)
    if n == 1:
        return np.array([area / max(float(lengths[0]), 1e-9)])
    pts, owner = _samples(beads, width / 6.0)
    # A ring of far points around the island: the unbounded cells are theirs, not a bead's (GEOS
    # leaves hull cells clipped to an envelope self-intersecting; bounded ones come out right).
    frame = _frame(island, width)
    allp = np.vstack([pts, frame])
    cells = shapely.get_parts(shapely.voronoi_polygons(shapely.multipoints(allp), ordered=True))
    if len(cells) != len(allp):  # degenerate input (GEOS merged points): share by length
        return np.full(n, area / max(float(lengths.sum()), 1e-12))
    cells = cells[:len(pts)]
    bad = ~shapely.is_valid(cells)  # GEOS can leave a sliver cell self-intersecting
    cells[bad] = shapely.make_valid(cells[bad])
    try:
        areas = _clipped_areas(cells, island, 4.0 * width)
    except shapely.errors.GEOSException:  # a topology conflict of nearly coincident edges: snap both
        areas = _clipped_areas(shapely.make_valid(shapely.set_precision(cells, 1e-6)),
                               shapely.make_valid(shapely.set_precision(island, 1e-6)), 4.0 * width)
    near = np.bincount(owner, weights=areas, minlength=n).astype(np.float64)
    near = near * (area / max(float(near.sum()), 1e-12))  # the cells tile the island: rounding only
    out: np.ndarray = near / np.maximum(lengths, 1e-9)
    return out


def _frame(island: Polygon, width: float) -> np.ndarray:
    """Points on a circle 2 w beyond the island's bounding box, about w apart."""
    minx, miny, maxx, maxy = island.bounds
    r = 0.5 * float(np.hypot(maxx - minx, maxy - miny)) + 2.0 * width
    k = int(2.0 * np.pi * r / width) + 8
    ang = np.arange(k) * (2.0 * np.pi / k)
    return np.column_stack([0.5 * (minx + maxx) + r * np.cos(ang), 0.5 * (miny + maxy) + r * np.sin(ang)])


FEW_CELLS = 48  # cells left to overlays below which each is clipped alone (tiles cost more to make)


def _clipped_areas(cells: np.ndarray, island: shapely.Geometry, tile_mm: float) -> np.ndarray:
    """Area of each cell inside the island. Cells wholly inside are not clipped; the others are
    clipped all at once (planner.cellclip); the few it leaves are clipped against the island cut to
    their boxes, or, when there are many, against tiles of the island (a grid of squares about
    `tile_mm` wide): each overlay then sees a few island edges."""
    shapely.prepare(island)
    areas = np.asarray(shapely.area(cells), dtype=np.float64)
    edge = np.flatnonzero(~shapely.contains(island, cells))
    if len(edge) == 0:
        return areas
    areas[edge], rest = cell_areas_inside(cells[edge], island)
    edge = edge[rest]  # the few cells the arrays could not decide (a corner on the boundary): overlays
    if len(edge) == 0:
        return areas
    if len(edge) <= FEW_CELLS:  # each against the island clipped to its own box: no grid of tiles to make
        local = [shapely.clip_by_rect(island, *shapely.bounds(c)) for c in cells[edge]]
        areas[edge] = shapely.area(shapely.intersection(cells[edge], np.array(local, dtype=object)))
        return areas
    minx, miny, maxx, maxy = island.bounds
    xs = np.arange(minx, maxx + tile_mm, tile_mm)
    ys = np.arange(miny, maxy + tile_mm, tile_mm)
    gx, gy = np.meshgrid(xs[:-1], ys[:-1])
    boxes = shapely.box(gx.ravel(), gy.ravel(), gx.ravel() + tile_mm, gy.ravel() + tile_mm)
    tiles = shapely.intersection(boxes, island)
    tiles = tiles[~shapely.is_empty(tiles)]
    ci, ti = shapely.STRtree(tiles).query(cells[edge], predicate="intersects")
    part = shapely.area(shapely.intersection(cells[edge][ci], tiles[ti]))
    areas[edge] = np.bincount(ci, weights=part, minlength=len(edge))
    return areas


def _samples(beads: Sequence[Path2D], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points along each bead and their bead: every vertex, `spacing` apart within 6·spacing (a
    bead width) of a vertex and 2·spacing apart along the middle of a longer straight segment
    (issue 40: the Voronoi diagram is most of the balance's time, and between two straight parallel
    runs the bisector of points sampled at any spacing bounds the same strip, so only corners,
    curves and ends need the fine spacing; against shares sampled 16 a width, the largest error
    stays as it was at one spacing throughout, docs/planner.md). Points of different beads closer
    than spacing/4 are kept once (a junction)."""
    xys = [np.asarray(b.points, dtype=np.float64) for b in beads]
    pts, owner = graded_points(xys, spacing, 2.0 * spacing, 6.0 * spacing)
    first = _first_of_each(np.round(pts / (0.25 * spacing)))
    return pts[first], owner[first]


def graded_points(xys: Sequence[np.ndarray], fine: float, coarse: float, near: float) -> tuple[np.ndarray, np.ndarray]:
    """(points, index of their polyline): each polyline's first vertex, then along each segment
    points `fine` apart within `near` of its ends and at most `coarse` apart between (a segment
    no longer than 2·near: `fine` apart throughout); every vertex is a point. Segments of length
    0 add nothing."""
    owner_seg = np.concatenate([np.full(len(xy) - 1, i, dtype=np.int64) for i, xy in enumerate(xys)])
    a = np.vstack([xy[:-1] for xy in xys])
    b = np.vstack([xy[1:] for xy in xys])
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    long_ = length > 2.0 * near
    end = np.where(long_, near, 0.5 * length)  # three pieces a segment: [0, e], [e, L - e], [L - e, L]
    lo = np.stack([np.zeros_like(length), end, length - end], axis=1).ravel()
    hi = np.stack([end, length - end, length], axis=1).ravel()
    step = np.stack([np.full_like(length, fine), np.where(long_, coarse, fine), np.full_like(length, fine)],
                    axis=1).ravel()
    n = np.where(hi > lo, np.ceil((hi - lo) / step - 1e-9), 0.0).astype(np.int64)
    piece = np.repeat(np.arange(len(n)), n)
    m = np.arange(len(piece)) - np.repeat(np.cumsum(n) - n, n) + 1  # 1..n within each piece
    t = lo[piece] + (hi[piece] - lo[piece]) * (m / n[piece])
    seg = piece // 3
    f = t / length[seg]  # a piece with points has a positive length
    pts = np.vstack([np.array([xy[0] for xy in xys]), a[seg] + d[seg] * f[:, None]])
    last = np.flatnonzero((m == n[piece]) & (piece % 3 == 2))
    pts[len(xys) + last] = b[seg[last]]  # a piece's last point: its end exactly
    return pts, np.concatenate([np.arange(len(xys), dtype=np.int64), owner_seg[seg]])


def _first_of_each(cells: np.ndarray) -> np.ndarray:
    """Ascending indices of the first row of each distinct row of integral floats: what
    np.unique(cells, axis=0, return_index=True)[1], sorted, gives (-0.0 is 0.0), by one sort of
    int64 keys when the values fit in 31 bits."""
    if len(cells) == 0 or float(np.max(np.abs(cells))) >= 2.0 ** 30:
        found: np.ndarray = np.unique(cells, axis=0, return_index=True)[1]
        return np.sort(found)
    ij = cells.astype(np.int64)
    key = (ij[:, 0] << 32) + ij[:, 1]
    order = np.argsort(key, kind="stable")
    sk = key[order]
    new = np.empty(len(sk), dtype=bool)
    new[0] = True
    np.not_equal(sk[1:], sk[:-1], out=new[1:])
    return np.sort(order[new])

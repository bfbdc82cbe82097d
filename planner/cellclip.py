"""Area of convex cells inside a polygon, every cell at once (the mass balance's Voronoi cells).

By Green's theorem the area of C ∩ P is ∮ x dy around its boundary, which is made of the
polygon's edges clipped to the cell (Liang–Barsky against the cell's half-planes) and of the
cell's edges clipped to the polygon: ∫ over an edge whose end is inside, and ±∫ up to each
crossing (− where the edge enters P, + where it leaves). Each (cell, polygon edge) pair is
independent, so all cells take a few array operations instead of one polygon overlay each
(issue 28: the overlays were a third of a torus's plan).

A cell whose crossings disagree with its corners' inside/outside (a corner on the polygon's
boundary, an edge through one of the polygon's vertices, edges along each other) is returned
as not done, for the caller to clip with GEOS. Each cell's sums are taken about its own first
corner, so they are sums of small numbers.
"""
from __future__ import annotations

import numpy as np
import shapely


def cell_areas_inside(cells: np.ndarray, polygon: shapely.Geometry) -> tuple[np.ndarray, np.ndarray]:
    """(area of each convex cell inside `polygon`, the indices of the cells left to the caller).

    `cells`: convex shapely Polygons without holes (a Voronoi diagram's cells); any other
    geometry is left to the caller. `polygon`: a Polygon, holes allowed."""
    out = np.zeros(len(cells))
    simple = (shapely.get_type_id(cells) == 3) & (shapely.get_num_interior_rings(cells) == 0)
    simple &= ~shapely.is_empty(cells)
    todo = np.flatnonzero(simple)
    if len(todo) == 0:
        return out, np.flatnonzero(~simple)
    corner, cell, nxt, origin, not_convex = _corners(cells[todo])
    inside = shapely.contains_xy(polygon, corner[:, 0], corner[:, 1])  # on the boundary: not inside
    p = corner - origin[cell]
    q = p[nxt]
    area = np.bincount(cell, weights=np.where(inside[nxt], _xdy(p, q, 1.0), 0.0), minlength=len(todo))
    pa, pb = _polygon_edges(polygon)
    ci, ei = shapely.STRtree(shapely.linestrings(np.stack([pa, pb], axis=1))).query(cells[todo])
    bad = _pairs(area, cell, p, q, ci, pa[ei] - origin[ci], pb[ei] - origin[ci], inside != inside[nxt])
    whole = np.asarray(shapely.area(cells[todo]))
    bad |= not_convex | (area < -1e-9 * whole) | (area > whole * (1.0 + 1e-9))
    out[todo] = np.clip(area, 0.0, whole)
    return out, np.sort(np.r_[np.flatnonzero(~simple), todo[bad]])


def _corners(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every cell's corners counter-clockwise, the cell of each, the index of the next corner
    round its cell, each cell's first corner, and the cells that are not convex polygons.

    A corner a rounding error away from the next one (GEOS leaves such pairs where Voronoi
    vertices nearly coincide) is dropped: the edge between them has no direction to clip with."""
    rings = shapely.get_exterior_ring(cells)
    xy, ring_of = shapely.get_coordinates(rings, return_index=True)
    n = len(cells)
    start = np.searchsorted(ring_of, np.arange(n))
    keep = np.ones(len(xy), dtype=bool)
    keep[np.r_[start[1:], len(xy)] - 1] = False  # the closing corner (a repeat of the first)
    size = np.hypot(*(np.asarray(shapely.bounds(cells))[:, 2:] - np.asarray(shapely.bounds(cells))[:, :2]).T)
    step = np.hypot(*(np.diff(xy, axis=0, append=xy[:1]).T))
    keep &= step > 1e-9 * size[ring_of]  # a corner within 1e-9 of the cell's size from the next one
    idx = np.flatnonzero(keep)
    cell = ring_of[idx]
    first = np.searchsorted(cell, np.arange(n))
    m = np.bincount(cell, minlength=n)
    j = np.arange(len(idx)) - first[cell]
    cw = ~shapely.is_ccw(rings)[cell]
    corner = xy[np.where(cw, idx[first[cell] + m[cell] - 1 - j], idx)]  # a clockwise ring read backwards
    k = np.arange(len(idx))
    nxt = np.where(j + 1 < m[cell], k + 1, k - j)
    d = corner[nxt] - corner
    turn = d[:, 0] * d[nxt, 1] - d[:, 1] * d[nxt, 0]
    reflex = turn < -1e-9 * np.hypot(*d.T) * np.hypot(*d[nxt].T)
    not_convex = (m < 3) | (np.bincount(cell, weights=reflex, minlength=n) > 0)
    return corner, cell, nxt, xy[start], not_convex


def _polygon_edges(polygon: shapely.Geometry) -> tuple[np.ndarray, np.ndarray]:
    """The polygon's edges (a, b), its interior on their left: shell counter-clockwise, holes clockwise."""
    oriented = shapely.orient_polygons(polygon, exterior_cw=False)
    a, b = [], []
    for geom in shapely.get_parts(oriented):
        for ring in (geom.exterior, *geom.interiors):
            c = np.asarray(ring.coords)
            a.append(c[:-1])
            b.append(c[1:])
    return np.vstack(a), np.vstack(b)


def _xdy(p: np.ndarray, q: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """∫ x dy along p→q from its start to parameter t."""
    d = q - p
    out: np.ndarray = d[:, 1] * (p[:, 0] * t + 0.5 * d[:, 0] * t * t)
    return out


def _pairs(area: np.ndarray, cell: np.ndarray, p: np.ndarray, q: np.ndarray, ci: np.ndarray, a: np.ndarray,
           b: np.ndarray, changes: np.ndarray) -> np.ndarray:
    """Add every (cell, polygon edge a→b) pair's terms to `area`; the cells whose crossings do not
    match their corners (`changes`: an edge's ends on different sides), to be clipped by GEOS."""
    n = len(area)
    bad = np.zeros(n, dtype=bool)
    if len(ci) == 0:
        bad[cell[changes]] = True
        return bad
    first = np.searchsorted(cell, np.arange(n))
    k = np.bincount(cell, minlength=n)[ci]  # rows: each pair × each edge of its cell
    starts = np.r_[0, np.cumsum(k)[:-1]]
    row_pair = np.repeat(np.arange(len(ci)), k)
    row_edge = first[ci][row_pair] + (np.arange(len(row_pair)) - starts[row_pair])
    pe, qe = p[row_edge], q[row_edge]
    d = qe - pe
    e = (b - a)[row_pair]
    w = a[row_pair] - pe
    den = d[:, 0] * e[:, 1] - d[:, 1] * e[:, 0]  # cross(d, e)
    num = d[:, 0] * w[:, 1] - d[:, 1] * w[:, 0]  # cross(d, a − p): a left of p→q when > 0
    # Liang–Barsky: a + u·e left of every edge p→q of the cell, 0 <= u <= 1
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = -num / den
    u0 = np.maximum(np.maximum.reduceat(np.where(den > 0, bound, -np.inf), starts), 0.0)
    u1 = np.minimum(np.minimum.reduceat(np.where(den < 0, bound, np.inf), starts), 1.0)
    shut = np.maximum.reduceat(((den == 0) & (num < 0)).view(np.int8), starts) > 0
    ea = b - a
    part = np.where((u1 > u0) & ~shut, ea[:, 1] * (a[:, 0] * (u1 - u0) + 0.5 * ea[:, 0] * (u1 * u1 - u0 * u0)), 0.0)
    area += np.bincount(ci, weights=part, minlength=n)
    # the cell's edges crossing the polygon's: p + t·d = a + u·e, counted for 0 < t <= 1, 0 <= u < 1
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / den
        u = (w[:, 0] * d[:, 1] - w[:, 1] * d[:, 0]) / den
    hit = (den != 0) & (t > 0) & (t <= 1) & (u >= 0) & (u < 1)
    rows = np.flatnonzero(hit)
    # cross(e, d) > 0 (den < 0): from the right of the polygon's edge to its left, into P: −∫
    sign = np.where(den[rows] < 0, -1.0, 1.0)
    area += np.bincount(cell[row_edge[rows]], weights=sign * _xdy(pe[rows], qe[rows], t[rows]), minlength=n)
    odd = (np.bincount(row_edge[rows], minlength=len(p)) % 2).astype(bool)
    bad[cell[odd != changes]] = True
    bad[ci[np.maximum.reduceat(((den == 0) & (num == 0)).view(np.int8), starts) > 0]] = True  # along an edge
    return bad

"""Closed contours of one layer → islands (shapely polygons with holes), by even-odd nesting."""
from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon


def islands(loops: list[np.ndarray], simplify_mm: float = 0.0) -> list[Polygon]:
    """Outer contours and holes classified by nesting depth (even: outer, odd: hole)."""
    loops = [lp for lp in loops if len(lp) >= 3]
    if not loops:
        return []
    coords = np.vstack(loops)
    idx = np.repeat(np.arange(len(loops)), [len(lp) for lp in loops])
    rings = shapely.linearrings(coords, indices=idx)
    polys = shapely.polygons(rings)
    areas = shapely.area(polys)
    ok = areas > 1e-9
    if not ok.all():
        loops = [lp for lp, k in zip(loops, ok) if k]
        polys, areas = polys[ok], areas[ok]
    if len(polys) == 0:
        return []
    # Depth = how many other loops contain a point of this loop.
    probe = shapely.points(np.array([lp[0] for lp in loops]))
    tree = shapely.STRtree(polys)
    pi, pj = tree.query(probe, predicate="within")
    depth = np.bincount(pi[pi != pj], minlength=len(polys))
    out: list[Polygon] = []
    shells = [i for i in np.argsort(-areas, kind="stable") if depth[i] % 2 == 0]
    holes_of: dict[int, list[int]] = {i: [] for i in shells}
    for h in np.flatnonzero(depth % 2 == 1):
        parents = [j for j in pj[(pi == h)] if depth[j] == depth[h] - 1 and j != h]
        if parents:
            holes_of[int(min(parents, key=lambda j: areas[j]))].append(int(h))
    for s in shells:
        poly = Polygon(loops[s], [loops[h] for h in holes_of[s]])
        if not poly.is_valid:
            poly = shapely.make_valid(poly)
        out.extend(_polygons(poly))
    if simplify_mm > 0:
        out = [g for p in out for g in _polygons(shapely.simplify(p, simplify_mm))]
    return [p for p in out if p.area > 1e-9]


def _polygons(geom: shapely.Geometry) -> list[Polygon]:
    if isinstance(geom, Polygon):
        return [] if geom.is_empty else [geom]
    if isinstance(geom, MultiPolygon):
        return [g for g in geom.geoms if not g.is_empty]
    if hasattr(geom, "geoms"):
        return [p for g in geom.geoms for p in _polygons(g)]
    return []


def polygons_of(geom: shapely.Geometry) -> list[Polygon]:
    """The polygons inside any shapely geometry (collections flattened, lines dropped)."""
    return _polygons(geom)

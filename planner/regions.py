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
    polys = shapely.polygons(shapely.linearrings(coords, indices=idx))
    areas = shapely.area(polys)
    ok = areas > 1e-9
    if not ok.all():
        loops = [lp for lp, k in zip(loops, ok) if k]
        polys, areas = polys[ok], areas[ok]
    if len(polys) == 0:
        return []
    out: list[Polygon] = []
    for shell, holes in _nesting(loops, polys, areas).items():
        poly = Polygon(loops[shell], [loops[h] for h in holes])
        out.extend(_polygons(poly if poly.is_valid else shapely.make_valid(poly)))
    if simplify_mm > 0:
        out = [g for p in out for g in _polygons(shapely.simplify(p, simplify_mm))]
    return [p for p in out if p.area > 1e-9]


def _nesting(loops: list[np.ndarray], polys: np.ndarray, areas: np.ndarray) -> dict[int, list[int]]:
    """Each outer loop (largest first) and its holes: depth = how many other loops contain a
    point of this loop; a hole belongs to the smallest loop one level up that contains it."""
    probe = shapely.points(np.array([lp[0] for lp in loops]))
    pi, pj = shapely.STRtree(polys).query(probe, predicate="within")
    depth = np.bincount(pi[pi != pj], minlength=len(polys))
    shells = [int(i) for i in np.argsort(-areas, kind="stable") if depth[i] % 2 == 0]
    holes_of: dict[int, list[int]] = {i: [] for i in shells}
    for h in np.flatnonzero(depth % 2 == 1):
        parents = [j for j in pj[(pi == h)] if depth[j] == depth[h] - 1 and j != h]
        if parents:
            holes_of[int(min(parents, key=lambda j: areas[j]))].append(int(h))
    return holes_of


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

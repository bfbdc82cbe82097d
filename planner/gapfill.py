"""Single centre-line beads for thin regions, from the polygon's medial axis (Voronoi edges)."""
from __future__ import annotations

import numpy as np
import shapely
import shapely.ops
from shapely.geometry import LineString, Polygon

from planner.path2d import Path2D
from planner.regions import polygons_of


def centre_lines(poly: Polygon, width: float, min_width: float = 0.0, depth: int = 3) -> list[Path2D]:
    """Centre-line beads covering a thin polygon, each as wide as the region around its axis.

    The longest medial-axis path is taken first; branches the first bead leaves uncovered get
    their own (up to `depth` rounds). Pockets narrower than `min_width` get none: the neighbouring
    beads flow into them.
    """
    out: list[Path2D] = []
    todo = [poly]
    for _ in range(depth):
        nxt = []
        for piece in todo:
            for bead in _axis_beads(piece, width, min_width):
                out.append(bead)
                rest = piece.difference(shapely.buffer(shapely.linestrings(bead.points), 0.5 * bead.width_mm))
                nxt += [g for g in polygons_of(rest) if g.area > 0.5 * width * width
                        and not g.buffer(-0.15 * width).is_empty]
        todo = nxt
        if not todo:
            break
    return out


def _axis_beads(poly: Polygon, width: float, min_width: float) -> list[Path2D]:
    import networkx as nx  # only thin parts need it: keep `cell plan` quick to start

    simple = shapely.simplify(poly, 0.02 * width)
    if simple.is_empty or simple.area <= 0:
        return []
    dense = shapely.segmentize(simple, width / 6.0)
    pts = shapely.get_coordinates(dense.boundary)
    if len(pts) < 4:
        return []
    edges = shapely.get_parts(shapely.voronoi_polygons(shapely.multipoints(pts), only_edges=True))
    shapely.prepare(simple)
    edges = edges[shapely.covered_by(edges, simple)]
    if len(edges) == 0:
        return []
    g = nx.Graph()
    for e in edges:
        c = np.round(np.asarray(e.coords), 6)
        for a, b in zip(c[:-1], c[1:]):
            la = float(np.hypot(*(b - a)))
            if la > 0:
                g.add_edge(tuple(a), tuple(b), weight=la)
    out = []
    boundary = simple.boundary
    for comp in sorted(nx.connected_components(g), key=lambda c: -len(c)):
        path, closed = _longest(g.subgraph(comp))
        if len(path) < 2:
            continue
        # Local width: twice the distance from the axis to the boundary (the inscribed circles).
        radii = shapely.distance(shapely.points(np.asarray(path)), boundary)
        r_med = float(np.median(radii))
        if not closed:
            # The axis runs out into the corners where the inscribed circle shrinks to nothing:
            # the bead stops where the circle is still most of the typical one (its cap fills the end).
            keep = np.flatnonzero(radii >= 0.7 * r_med)
            path = path[keep[0]:keep[-1] + 1]
        if len(path) < 2:
            continue
        line = LineString(path)
        if line.length < 0.25 * width:
            continue
        w_raw = 2.0 * r_med
        if w_raw < min_width:
            continue
        w_est = float(np.clip(w_raw, 0.3 * width, 1.5 * width))
        pts = np.asarray(line.simplify(0.02 * width).coords)[:, :2]
        if closed:
            pts = np.vstack([pts, pts[:1]])
        out.append(Path2D("gap", pts, w_est, closed=closed, share_mm=w_est))
    return out


def _longest(g) -> tuple[list, bool]:
    """The longest cycle if the axis has one (a ring), else the tree's diameter path."""
    import networkx as nx

    if g.number_of_edges() >= g.number_of_nodes():
        cycles = nx.cycle_basis(g)
        if cycles:
            best = max(cycles, key=lambda c: sum(g[c[i]][c[(i + 1) % len(c)]]["weight"] for i in range(len(c))))
            return best, True
    start = next(iter(g.nodes))
    d1 = nx.single_source_dijkstra_path_length(g, start)
    far = max(d1, key=d1.get)
    _, paths = nx.single_source_dijkstra(g, far)
    dist = nx.single_source_dijkstra_path_length(g, far)
    other = max(dist, key=dist.get)
    return paths[other], False

"""Single centre-line beads for thin regions, from the polygon's medial axis (Voronoi edges)."""
from __future__ import annotations

import networkx as nx
import numpy as np
import shapely
from shapely.geometry import LineString, Polygon

from planner.path2d import Path2D


def centre_lines(poly: Polygon, width: float, min_width: float = 0.0) -> list[Path2D]:
    """Centre-line beads covering a thin polygon; each bead's width is the region's mean width.

    Pockets narrower than `min_width` get none: the neighbouring beads flow into them.
    """
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
    for comp in sorted(nx.connected_components(g), key=lambda c: -len(c)):
        sub = g.subgraph(comp)
        path, closed = _longest(sub)
        if len(path) < 2:
            continue
        line = LineString(path)
        if line.length < 0.25 * width:
            continue
        w_raw = simple.area / max(line.length, 1e-9)
        if w_raw < min_width:
            continue
        w_est = float(np.clip(w_raw, 0.3 * width, 1.5 * width))
        if not closed:
            # The medial axis runs into the corners: stop half a bead short of the ends.
            trim = min(0.5 * w_est, 0.3 * line.length)
            line = shapely.ops.substring(line, trim, line.length - trim)
        pts = np.asarray(line.simplify(0.02 * width).coords)[:, :2]
        if closed:
            pts = np.vstack([pts, pts[:1]])
        out.append(Path2D("gap", pts, w_est, closed=closed, share_mm=w_est))
    return out


def _longest(g: nx.Graph) -> tuple[list, bool]:
    """The longest cycle if the axis has one (a ring), else the tree's diameter path."""
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

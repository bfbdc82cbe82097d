"""Single centre-line beads for thin regions, from the polygon's medial axis (Voronoi edges).

The axis graph (a few hundred nodes per piece) is searched with heapq Dijkstra (no networkx, no
scipy import at start-up), and the result is memoised per polygon: a prismatic wall gives the
same piece on every layer.
"""
from __future__ import annotations

import heapq
from functools import lru_cache

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon

from planner.path2d import Path2D
from planner.regions import polygons_of


def centre_lines(poly: Polygon, width: float, min_width: float = 0.0, depth: int = 3) -> list[Path2D]:
    """Centre-line beads covering a thin polygon, each as wide as the region around its axis.

    The longest medial-axis path is taken first; branches the first bead leaves uncovered get
    their own (up to `depth` rounds). Pockets narrower than `min_width` get none: the neighbouring
    beads flow into them.
    """
    key = shapely.to_wkb(shapely.set_precision(poly, 1e-6))
    return [Path2D("gap", pts, w, closed, w) for pts, w, closed in
            _centre_lines(key, round(width, 9), round(min_width, 9), depth)]


def pocket_line(poly: Polygon, width: float, min_width: float) -> list[Path2D]:
    """A small pocket's bead directly: the long axis of its minimum rotated rectangle, ended half
    its width short of the rectangle's ends (the round cap fills them); as wide as its mean width."""
    rect = np.asarray(shapely.oriented_envelope(poly).exterior.coords)[:4]
    if len(rect) < 4:
        return []
    e1, e2 = rect[1] - rect[0], rect[2] - rect[1]
    a, b = (e1, e2) if np.hypot(*e1) >= np.hypot(*e2) else (e2, e1)
    length = float(np.hypot(*a))
    w_mean = poly.area / max(length, 1e-9)
    if w_mean < min_width or length <= 0:
        return []
    centre = rect.mean(axis=0)
    half = 0.5 * max(length - w_mean, 0.25 * width) * a / length
    w_est = float(np.clip(w_mean, 0.3 * width, 1.5 * width))
    return [Path2D("gap", np.array([centre - half, centre + half]), w_est, False, w_est)]


@lru_cache(maxsize=4096)
def _centre_lines(key: bytes, width: float, min_width: float, depth: int) -> tuple[tuple[np.ndarray, float, bool], ...]:
    out = []
    todo = [shapely.from_wkb(key)]
    for _ in range(depth):
        nxt = []
        for piece in todo:
            for pts, w, closed in _axis_beads(piece, width, min_width):
                pts.setflags(write=False)
                out.append((pts, w, closed))
                rest = piece.difference(shapely.buffer(shapely.linestrings(pts), 0.5 * w))
                nxt += [g for g in polygons_of(rest) if g.area > 0.5 * width * width
                        and not g.buffer(-0.15 * width).is_empty]
        todo = nxt
        if not todo:
            break
    return tuple(out)


def _axis_graph(poly: Polygon, width: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Voronoi edges of the densified boundary inside the polygon, as (nodes, i, j, lengths)."""
    dense = shapely.segmentize(poly, width / 4.0)
    pts = shapely.get_coordinates(dense.boundary)
    if len(pts) < 4:
        return None
    edges = shapely.get_parts(shapely.voronoi_polygons(shapely.multipoints(pts), only_edges=True))
    shapely.prepare(poly)
    edges = edges[shapely.covered_by(edges, poly)]
    if len(edges) == 0:
        return None
    coords, idx = shapely.get_coordinates(edges, return_index=True)
    same = idx[1:] == idx[:-1]
    a, b = coords[:-1][same], coords[1:][same]
    nodes, inv = np.unique(np.round(np.vstack([a, b]), 6), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    i, j = inv[:len(a)], inv[len(a):]
    length = np.hypot(*(b - a).T)
    keep = (i != j) & (length > 0)
    i, j, length = i[keep], j[keep], length[keep]
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    _, first = np.unique(lo * len(nodes) + hi, return_index=True)  # one edge per node pair
    return nodes, lo[first], hi[first], length[first]


def _median(x: np.ndarray) -> float:
    """np.median of a non-empty 1-D array, the same number, without its first call's import of
    numpy.ma (about 30 ms of start-up, issue 28)."""
    s = np.sort(x)
    k = len(s) // 2
    return float(s[k]) if len(s) % 2 else float((s[k - 1] + s[k]) / 2.0)


def _axis_beads(poly: Polygon, width: float, min_width: float) -> list[tuple[np.ndarray, float, bool]]:
    simple = shapely.simplify(poly, 0.02 * width)
    if simple.is_empty or simple.area <= 0:
        return []
    graph = _axis_graph(simple, width)
    if graph is None:
        return []
    nodes, i, j, length = graph
    adj: dict[int, list[tuple[int, float]]] = {}
    for a, b, ln in zip(i.tolist(), j.tolist(), length.tolist()):
        adj.setdefault(a, []).append((b, ln))
        adj.setdefault(b, []).append((a, ln))
    out = []
    boundary = simple.boundary
    for members in sorted(_components(adj), key=len, reverse=True):
        if len(members) < 2:
            continue
        order, closed = _longest(adj, members, i, j)
        if len(order) < 2:
            continue
        path = nodes[order]
        # Local width: twice the distance from the axis to the boundary (the inscribed circles).
        radii = shapely.distance(shapely.points(path), boundary)
        r_med = _median(radii)
        if not closed:
            # The axis runs out into the corners where the inscribed circle shrinks to nothing:
            # the bead stops where the circle is still nearly the typical one (its cap fills the end).
            keep = np.flatnonzero(radii >= 0.97 * r_med)
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
        out.append((pts, w_est, closed))
    return out


def _components(adj: dict[int, list[tuple[int, float]]]) -> list[list[int]]:
    seen: set[int] = set()
    comps = []
    for start in sorted(adj):
        if start in seen:
            continue
        stack, comp = [start], []
        seen.add(start)
        while stack:
            u = stack.pop()
            comp.append(u)
            for v, _ in adj[u]:
                if v not in seen:
                    seen.add(v)
                    stack.append(v)
        comps.append(sorted(comp))
    return comps


def _dijkstra(adj: dict[int, list[tuple[int, float]]], src: int) -> tuple[dict[int, float], dict[int, int]]:
    dist, pred = {src: 0.0}, {}
    heap = [(0.0, src)]
    while heap:
        d, u = heapq.heappop(heap)
        if d > dist[u]:
            continue
        for v, ln in adj[u]:
            nd = d + ln
            if nd < dist.get(v, np.inf):
                dist[v], pred[v] = nd, u
                heapq.heappush(heap, (nd, v))
    return dist, pred


def _longest(adj: dict[int, list[tuple[int, float]]], members: list[int], i: np.ndarray,
             j: np.ndarray) -> tuple[list[int], bool]:
    """The cycle if the axis is a ring (its 2-core), else the tree's diameter path."""
    inside = set(members)
    e_in = np.array([a in inside for a in i.tolist()], dtype=bool)
    if int(e_in.sum()) >= len(members):
        cyc = _cycle(np.asarray(members), i[e_in], j[e_in])
        if cyc is not None:
            return cyc, True
    d1, _ = _dijkstra(adj, members[0])
    far = max(d1, key=lambda k: (d1[k], -k))
    d2, pred = _dijkstra(adj, far)
    other = max(d2, key=lambda k: (d2[k], -k))
    path = [other]
    while path[-1] != far:
        path.append(pred[path[-1]])
    return path[::-1], False


def _cycle(members: np.ndarray, i: np.ndarray, j: np.ndarray) -> list[int] | None:
    """The single cycle left after pruning the axis's leaves; None if it is not one simple cycle."""
    ei, ej = i.copy(), j.copy()
    while len(ei):
        deg = np.bincount(np.concatenate([ei, ej]), minlength=int(members.max()) + 1)
        leaf = deg == 1
        drop = leaf[ei] | leaf[ej]
        if not drop.any():
            break
        ei, ej = ei[~drop], ej[~drop]
    if len(ei) < 3:
        return None
    deg = np.bincount(np.concatenate([ei, ej]))
    if np.any(deg[np.unique(np.concatenate([ei, ej]))] != 2):
        return None  # several cycles: take the diameter path instead
    nbr: dict[int, list[int]] = {}
    for a, b in zip(ei.tolist(), ej.tolist()):
        nbr.setdefault(a, []).append(b)
        nbr.setdefault(b, []).append(a)
    start = min(nbr)
    path, prev, cur = [start], -1, start
    while True:
        nxt = nbr[cur][0] if nbr[cur][0] != prev else nbr[cur][1]
        if nxt == start:
            break
        path.append(nxt)
        prev, cur = cur, nxt
        if len(path) > len(nbr):
            return None
    return path if len(path) == len(nbr) else None

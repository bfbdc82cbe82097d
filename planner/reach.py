"""Variable bead width before "unplannable" (issue 28 item 2): what the nominal beads leave of an
island under --min-coverage gets extra gap beads of a narrower legal width, each with its own
welding point from the process model (planner.weld), where such a bead fits.

A piece left uncovered is followed along its medial axis by a bead as wide as the piece (inside the
legal widths [lo, hi] at the layer height); the bead's centre line is kept where a bead of that
width fits inside the island (the island eroded by half the width), snapped onto that limit
elsewhere, so a sliver along the contour is filled by a narrow bead hugging the wall. Beads
shorter than the minimum length are not made. Pure: no I/O, no clocks.
"""
from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon

from planner.gapfill import centre_lines
from planner.path2d import Path2D
from planner.regions import polygons_of
from planner.thin import Widths


def footprint(beads: list[Path2D]) -> shapely.Geometry:
    lines = np.array([shapely.linestrings(b.points) for b in beads], dtype=object)
    widths = np.array([b.width_mm for b in beads])
    return shapely.union_all(shapely.buffer(lines, widths / 2.0, quad_segs=4))


def reach_fill(island: Polygon, beads: list[Path2D], wd: Widths, min_coverage: float,
               min_length: float, allowance_mm: float = 0.0) -> list[Path2D]:
    """Extra narrow beads for an island whose beads cover less than `min_coverage` of it; near-net
    (`allowance_mm` > 0) a bead may stand out of the (grown) island by up to the allowance."""
    if not beads or island.area <= 0:
        return []
    rest = island.difference(footprint(beads))
    # near-net, a hole a legal bead fits in is filled even where the island is covered enough: a large
    # island hides a hole where a thin piece meets the body, and the net part may lie in it (issue 40)
    smallest = 0.25 * wd.lo * wd.lo
    if rest.area <= (1.0 - min_coverage) * island.area:
        if allowance_mm <= 0.0:
            return []
        smallest = wd.lo * wd.lo
    out: list[Path2D] = []
    rooms: dict[float, shapely.Geometry] = {}  # the island eroded for a bead of each width, made once
    for piece in polygons_of(rest):
        if piece.area < smallest:
            continue
        for axis in centre_lines(piece, wd.lo, depth=1):
            w = float(np.clip(axis.width_mm, wd.lo, wd.hi))
            pts = _inside(axis.points, island, w, allowance_mm, rooms)
            if pts is None:
                continue
            bead = Path2D("gap", pts, w, axis.closed)
            if allowance_mm > 0.0 and not axis.closed and bead.length < min_length:
                # near-net: a pocket bead runs on over its neighbours to the minimum length (their
                # shares are drawn after it, so the metal stays balanced); still short, no_stubs
                # welds it onto a neighbour or drops it, named
                longer = _inside(_extended(pts, min_length), island, w, allowance_mm, rooms)
                bead = Path2D("gap", longer, w) if longer is not None else bead
                if bead.length >= w:
                    out.append(bead)
            elif bead.length >= min_length:
                out.append(bead)
    return out


def run_on(beads: list[Path2D], island: Polygon, min_length: float, allowance_mm: float) -> list[Path2D]:
    """Near-net: open gap beads shorter than the minimum length run on straight over their
    neighbours to it, within the allowance of the island (instead of being dropped as stubs)."""
    if allowance_mm <= 0.0:
        return beads
    rooms: dict[float, shapely.Geometry] = {}
    out = []
    for b in beads:
        if b.closed or b.lone or b.length >= min_length or len(b.points) < 2:
            out.append(b)
            continue
        longer = _inside(_extended(np.asarray(b.points, dtype=np.float64), min_length), island, b.width_mm,
                         allowance_mm, rooms)
        out.append(Path2D(b.role, longer, b.width_mm, False, b.share_mm) if longer is not None else b)
    return out


def _extended(pts: np.ndarray, length: float) -> np.ndarray:
    """An open centre line run on straight at both ends to `length` (half the shortfall each)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    more = 0.5 * (length - float(seg.sum())) + 1e-3
    d0, d1 = pts[0] - pts[1], pts[-1] - pts[-2]
    d0, d1 = d0 / max(float(np.hypot(*d0)), 1e-12), d1 / max(float(np.hypot(*d1)), 1e-12)
    return np.vstack([pts[0] + more * d0, pts, pts[-1] + more * d1])


def _inside(points: np.ndarray, island: Polygon, width: float, allowance_mm: float = 0.0,
            rooms: dict[float, shapely.Geometry] | None = None) -> np.ndarray | None:
    """The centre line moved where a bead `width` wide stays inside the island (near-net: within the
    allowance of it); None if it cannot. `rooms` keeps the eroded island per width."""
    rooms = {} if rooms is None else rooms
    if width not in rooms:
        rooms[width] = island.buffer(allowance_mm - 0.49 * width, quad_segs=8)
        shapely.prepare(rooms[width])
    room = rooms[width]
    if room.is_empty:
        return None
    pts = np.array(points, dtype=np.float64)  # a copy: the medial-axis points are shared, read-only
    out = ~shapely.contains_xy(room, pts[:, 0], pts[:, 1])
    if out.any():
        edge = room.boundary
        at = shapely.line_locate_point(edge, shapely.points(pts[out]))
        pts[out] = shapely.get_coordinates(shapely.line_interpolate_point(edge, at))
    keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6]
    pts = pts[keep]
    return pts if len(pts) >= 2 else None

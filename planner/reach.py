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

COVERAGE_MARGIN = 0.005  # near-net: extra beads are laid until an island is this much over --min-coverage
NET_HOLE = 0.25  # near-net: a hole holding this much of the net part (x the narrowest bead squared) gets its bead


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
            bead = _reach_bead(axis, island, wd, min_length, allowance_mm, rooms)
            if bead is not None:
                out.append(bead)
    if allowance_mm <= 0.0:
        return out
    return _worth_it(out, island, rest, min_coverage, allowance_mm, wd.lo)


def _reach_bead(axis: Path2D, island: Polygon, wd: Widths, min_length: float, allowance_mm: float,
                rooms: dict[float, shapely.Geometry]) -> Path2D | None:
    """The bead along one uncovered piece's axis, as wide as the piece within the legal widths."""
    w = float(np.clip(axis.width_mm, wd.lo, wd.hi))
    pts = _inside(axis.points, island, w, allowance_mm, rooms)
    if pts is None:
        return None
    bead = Path2D("gap", pts, w, axis.closed)
    if allowance_mm > 0.0 and not axis.closed and bead.length < min_length:
        # near-net: a pocket bead runs on over its neighbours to the minimum length (their
        # shares are drawn after it, so the metal stays balanced); still short, no_stubs
        # welds it onto a neighbour or drops it, named
        longer = _inside(_extended(pts, min_length), island, w, allowance_mm, rooms)
        bead = Path2D("gap", longer, w) if longer is not None else bead
        return bead if bead.length >= w else None
    return bead if bead.length >= min_length else None


def _worth_it(beads: list[Path2D], island: Polygon, rest: shapely.Geometry, min_coverage: float,
              allowance_mm: float, narrowest: float) -> list[Path2D]:
    """Near-net: the extra beads worth their metal outside the island (issue 40: the octagonal pocket
    at 8 mm stood 1.63 % out of its grown region, a 5.2 mm wall at 8 mm 14 %, mostly these beads).
    Taken by the least metal outside per area they cover: while the island is under --min-coverage
    (with a margin) a bead that covers at least half what it puts outside; once covered enough, one
    that covers at least twice what it puts outside, or that covers the net part (the island shrunk
    by the allowance: it holds the part) where it lies in the hole (a thin ring meeting the body)."""
    if not beads:
        return beads
    fps = shapely.buffer(np.array([shapely.linestrings(b.points) for b in beads], dtype=object),
                         np.array([0.5 * b.width_mm for b in beads]), quad_segs=4)
    gain = shapely.area(shapely.intersection(fps, rest))
    spill = shapely.area(shapely.difference(fps, island))
    net_hole = rest.intersection(island.buffer(-allowance_mm, quad_segs=8))
    on_net = shapely.area(shapely.intersection(fps, net_hole)) >= NET_HOLE * narrowest * narrowest
    short = (min_coverage + COVERAGE_MARGIN) * island.area - (island.area - rest.area)
    out = []
    for k in sorted(range(len(beads)), key=lambda k: spill[k] / max(gain[k], 1e-9)):
        if gain[k] <= 0.0:
            continue
        if (short > 0.0 and spill[k] <= 2.0 * gain[k]) or spill[k] <= 0.5 * gain[k] or on_net[k]:
            out.append(beads[k])
            short -= gain[k]
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


def lone_ends(beads: list[Path2D], island: Polygon, min_coverage: float, allowance_mm: float,
              step_mm: float = 0.1) -> list[Path2D]:
    """Near-net: the open lone beads of an island under --min-coverage run on at their ends, a step at a
    time, until the island is covered (with a margin) or the ends would stand out of it by more than
    the allowance. A lone bead stops where its wall's inscribed circle shrinks, and its round cap
    leaves the corners of the grown wall's end (a 5.2 mm wall at 8 mm beads, 8.2 mm grown: 95.6 %
    covered; run on 1 mm, 97.1 %, its caps 1 % out of the grown region)."""
    lone = [k for k, b in enumerate(beads) if b.lone and not b.closed and len(b.points) >= 2]
    if allowance_mm <= 0.0 or not lone or island.area <= 0.0:
        return beads
    target = (min_coverage + 0.2 * COVERAGE_MARGIN) * island.area  # each step puts more out than it covers
    rooms: dict[float, shapely.Geometry] = {}
    out = list(beads)
    covered = float(island.intersection(footprint(out)).area)
    run = step_mm
    while covered < target and run <= allowance_mm + 1e-9:
        longer = list(out)
        for k in lone:
            b = beads[k]
            pts = _ends_run_on(np.asarray(b.points, dtype=np.float64), run, island, b.width_mm, allowance_mm, rooms)
            longer[k] = Path2D(b.role, pts, b.width_mm, False, b.share_mm, b.lone)
        now = float(island.intersection(footprint(longer)).area)
        if now <= covered + 1e-6:
            break
        out, covered = longer, now
        run += step_mm
    return out


def _ends_run_on(pts: np.ndarray, run: float, island: Polygon, width: float, allowance_mm: float,
                 rooms: dict[float, shapely.Geometry]) -> np.ndarray:
    """A centre line with each end run on straight by `run`, where the new end stays within the room a
    bead that wide has standing out of the island by at most the allowance (else that end stays)."""
    if width not in rooms:
        rooms[width] = island.buffer(allowance_mm - 0.49 * width, quad_segs=8)
        shapely.prepare(rooms[width])
    room = rooms[width]
    d0, d1 = pts[0] - pts[1], pts[-1] - pts[-2]
    n0, n1 = max(float(np.hypot(*d0)), 1e-12), max(float(np.hypot(*d1)), 1e-12)
    a, b = pts[0] + run * d0 / n0, pts[-1] + run * d1 / n1
    ok = shapely.contains_xy(room, np.array([a[0], b[0]]), np.array([a[1], b[1]]))
    return np.vstack([a[None, :]] * bool(ok[0]) + [pts] + [b[None, :]] * bool(ok[1]))

"""Scan-line infill linked zigzag into continuous beads (Fang 2019 §1.5, Kerschbaumer 2004)."""
from __future__ import annotations

from typing import Any

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import LineString, Polygon

from planner.path2d import Path2D
from planner.regions import polygons_of


def row_count(span: float, step: float, min_spacing: float, max_spacing: float) -> tuple[int, float]:
    """Rows across `span` with the first and last on its edges, spaced as near `step` as the
    stable band [min_spacing, max_spacing] allows (Ding 2015); (rows, spacing)."""
    if span < min_spacing or span <= 0.25 * step:
        return 1, step  # two rows this close would be unstable: one down the middle
    k = max(1, int(round(span / step)))
    if span / k < min_spacing and k > 1:
        k -= 1  # too close is unstable: one row fewer, a little wider apart
    if span / k > max_spacing:
        k += 1  # too far leaves a groove: one row more
    return k + 1, span / k


def scan_fill(region: shapely.Geometry, step: float, width: float, angle_deg: float, min_spacing: float | None = None) -> list[Path2D]:
    """Fill `region` (bead centres may go anywhere in it) with scan lines near `step`, linked zigzag."""
    out: list[Path2D] = []
    lo = step if min_spacing is None else min_spacing
    for piece in polygons_of(region):
        rot = affinity.rotate(piece, -angle_deg, origin=(0.0, 0.0))
        span = rot.bounds[3] - rot.bounds[1]
        n, spacing = row_count(span, step, lo, 0.92 * width)
        for chain in _zigzag(rot, step, spacing, n):
            pts = np.asarray(affinity.rotate(LineString(chain), angle_deg, origin=(0.0, 0.0)).coords)
            out.append(Path2D("infill", pts, width, closed=False, share_mm=spacing))
    return out


def _rows(poly: Polygon, n: int) -> list[tuple[float, list[tuple[float, float]]]]:
    minx, miny, maxx, maxy = poly.bounds
    span = maxy - miny
    # First and last lines on the region's edges (d* from the last perimeter), `n` rows.
    ys = miny + (np.linspace(0.0, span, n) if n > 1 else np.array([0.5 * span]))
    # A line exactly through a vertex is nudged, as in Fang 2019, so crossings come in pairs.
    ys = np.clip(ys, miny + 1e-6, maxy - 1e-6)
    lines = shapely.linestrings(np.stack([np.stack([np.full(n, minx - 1), ys], 1),
                                          np.stack([np.full(n, maxx + 1), ys], 1)], 1))
    cut = shapely.intersection(lines, poly)
    rows = []
    for y, g in zip(ys, cut):
        segs = []
        for part in shapely.get_parts(g):
            if isinstance(part, LineString) and part.length > 1e-6:
                xs = np.asarray(part.coords)[:, 0]
                segs.append((float(xs.min()), float(xs.max())))
        if segs:
            rows.append((float(y), sorted(segs)))
    return rows


def _zigzag(poly: Polygon, step: float, spacing: float, n: int) -> list[list[tuple[float, float]]]:
    """Link each row's segments to an overlapping segment of the next row at the same side."""
    corridor = poly.buffer(0.6 * step)
    shapely.prepare(corridor)
    chains: list[dict[str, Any]] = []
    active: list[dict[str, Any]] = []
    prev_y = None
    for y, segs in _rows(poly, n):
        used = [False] * len(segs)
        nxt_active = []
        adjacent = prev_y is not None and abs(y - prev_y - spacing) < 1e-6 * max(1.0, step)
        for ch in sorted(active, key=lambda c: c["seg"][0]) if adjacent else []:
            x0, x1 = ch["seg"]
            ex = ch["pts"][-1][0]
            side = ch["side"]
            best, best_d = -1, np.inf
            for j, (a, b) in enumerate(segs):
                if used[j] or b < x0 or a > x1:
                    continue
                sx = b if side == "R" else a
                if abs(sx - ex) < best_d:
                    best, best_d = j, abs(sx - ex)
            if best < 0:
                continue
            a, b = segs[best]
            start, end = ((b, y), (a, y)) if side == "R" else ((a, y), (b, y))
            conn = LineString([ch["pts"][-1], start])
            if conn.length > 3.0 * step or not corridor.covers(conn):
                continue
            used[best] = True
            ch["pts"] += [start, end]
            ch["seg"] = (a, b)
            ch["side"] = "L" if side == "R" else "R"
            nxt_active.append(ch)
        for j, (a, b) in enumerate(segs):
            if not used[j]:
                ch = {"pts": [(a, y), (b, y)], "seg": (a, b), "side": "R"}
                chains.append(ch)
                nxt_active.append(ch)
        active = nxt_active
        prev_y = y
    return [c["pts"] for c in chains]

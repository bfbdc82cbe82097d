"""Near-net planning (docs/contract.md §3.9): the part built oversize by a machining allowance, then machined.

* The grown region is the part grown by the allowance `a` in 3-D (every point within `a` of the
  part, issue 40): a layer's islands grow outward by `a` (round offsets, holes shrink by it), and
  a layer within `a` of another (dz < a) also holds that layer grown by sqrt(a² − dz²) — the stock
  under an overhang or over a step belongs to the layer it lies in. The part's top grows by `a`
  too: layers repeating the top layer's grown region are added until the deposit stands at least
  `a` above the net top. The bottom stands on the substrate and is not grown.
* Coverage, outside and mass balance are then judged against the grown region, and so is what
  is too narrow for a bead: a bead may stand out of the grown region by up to `a` (the stock there
  at most 2a), so a thin piece of the grown region narrower than the smallest legal bead, or
  between fits, is built with beads for the nearest width that fits (`stretch`), and only what no
  legal bead fills even so is refused, naming the allowance that would build it (`allowance_for`).
  A small island no bead of the minimum length fits in gets one closed loop (`small_loop`).
* Stock left to machine per face: on the sides, the distance from the net contour out to the
  edge of the beads' footprint (min and max over the layers; negative where the beads do not
  reach the net surface), on the top the deposit's height over the net top, at the bottom 0.
* A thin feature refused at the net size names the allowance that would make it buildable
  (`allowance_for`).

Pure: no I/O, no clocks.
"""
from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon

from planner.gapfill import centre_lines
from planner.path2d import Path2D
from planner.regions import polygons_of
from planner.thin import Widths, layout

STEP_MM = 0.05  # resolution of the allowance a refused feature is told it needs


def grow(polys: list[Polygon], allowance_mm: float) -> list[Polygon]:
    """The islands grown outward by the allowance (islands closer than 2a merge)."""
    if allowance_mm <= 0.0 or not polys:
        return polys
    grown = shapely.union_all(shapely.buffer(np.asarray(polys, dtype=object), allowance_mm, quad_segs=8))
    return [p for p in polygons_of(grown) if p.area > 1e-9]


def snapped(polys: list[Polygon]) -> list[Polygon]:
    """Islands snapped onto a 1e-6 mm grid: a union of offsets can leave two collinear edges a hair apart,
    on which GEOS's later overlays fail (a non-noded intersection: the angle block near-net at 4 mm)."""
    if not polys:
        return polys
    snap = shapely.set_precision(np.asarray(polys, dtype=object), 1e-6)
    return [p for s in snap for p in polygons_of(s) if p.area > 1e-9]


def grow_layers(nets: list[list[Polygon]], allowance_mm: float, layer_mm: float) -> list[list[Polygon]]:
    """Every layer's region grown by the allowance in 3-D (the part's points within `a`): its own
    islands grown by a, and those of each layer dz < a away grown by sqrt(a² − dz²). A neighbour
    whose islands this layer's cover adds nothing (its offset is inside this layer's own)."""
    if allowance_mm <= 0.0:
        return nets
    reach = int(math.floor(allowance_mm / layer_mm - 1e-9))
    unions = [shapely.set_precision(shapely.union_all(n), 1e-6) if n else Polygon() for n in nets]
    first: dict[bytes, int] = {}
    ids = [first.setdefault(shapely.to_wkb(shapely.normalize(u)) if n else b"", j)  # the first layer alike
           for j, (u, n) in enumerate(zip(unions, nets))]
    # a neighbour inside this layer (the wall above a pocket's floor, a boss above its plate) adds
    # nothing either: a layer grows from the neighbours that stick out of it only, so the layers
    # that grow the same repeat (their plan is the memo's, planner.plan)
    for u in unions:
        shapely.prepare(u)
    inside: dict[tuple[int, int], bool] = {}
    out: list[list[Polygon]] = []
    for i, net in enumerate(nets):
        parts = list(net)
        radii = [allowance_mm] * len(net)
        for k in range(max(0, i - reach), min(len(nets), i + reach + 1)):
            if k == i or not nets[k] or ids[k] == ids[i] or _covers(unions, ids[i], ids[k], inside):
                continue
            r = math.sqrt(max(allowance_mm ** 2 - ((k - i) * layer_mm) ** 2, 0.0))
            parts += nets[k]
            radii += [r] * len(nets[k])
        if not parts:
            out.append([])
            continue
        grown = shapely.union_all(shapely.buffer(np.asarray(parts, dtype=object), np.asarray(radii), quad_segs=8))
        out.append([p for p in polygons_of(grown) if p.area > 1e-9])
    return out


def supported(grown: list[list[Polygon]], step_mm: float, allowance_mm: float,
              min_area_mm2: float = 0.0) -> list[list[Polygon]]:
    """Near-net: the stock under an overhang of the grown region filled, from the top down, so that
    no layer steps out over the one below by more than `step_mm` (the overhang rule's step, with a
    margin): a layer holds the layer above shrunk by the step, where that lies within the allowance
    of its own grown region (the stock a bead may stand in). The roof of a hole the allowance has
    narrowed to a slot is built on the stock under it, and machined away with the rest; an overhang
    beyond the allowance (a lip, an underside) stays one, and the verdict names it (issue 40). A piece
    of stock standing apart from the layer's region and smaller than `min_area_mm2` (no bead builds it:
    the angle block at 4 mm got 0.2-6 mm² islands named as features no bead fills) is not added: the
    layer above then overhangs there, and the verdict names that."""
    if step_mm <= 0.0 or allowance_mm <= 0.0 or len(grown) < 2:
        return grown
    out = list(grown)
    above = shapely.union_all(out[-1]) if out[-1] else Polygon()
    for i in range(len(out) - 2, -1, -1):
        here = shapely.union_all(grown[i]) if grown[i] else Polygon()
        if above.is_empty or here.is_empty:
            above = here
            continue
        need = above.buffer(-step_mm, quad_segs=8)
        shapely.prepare(here)
        if need.is_empty or here.covers(need):
            above = here
            continue
        extra = need.difference(here).intersection(here.buffer(allowance_mm, quad_segs=8))
        if extra.area > 1e-6:
            old = here
            here = shapely.union_all([here, extra])
            out[i] = [p for p in polygons_of(here) if p.area > 1e-9 and (
                p.area >= min_area_mm2 or shapely.intersection(p, old).area > 1e-6)]
            here = shapely.union_all(out[i]) if out[i] else Polygon()
        above = here
    return out


def _covers(unions: list[shapely.Geometry], a: int, b: int, memo: dict[tuple[int, int], bool]) -> bool:
    """Whether layer a's islands cover layer b's (a and b the first layers with their islands: a
    prism asks once)."""
    if (a, b) not in memo:
        memo[(a, b)] = bool(shapely.covers(unions[a], unions[b]))
    return memo[(a, b)]


def layer_count(height_mm: float, layer_mm: float, allowance_mm: float, net_layers: int) -> int:
    """Layers of the near-net deposit: the net ones, and enough more for the top to stand `a` over it."""
    if allowance_mm <= 0.0:
        return net_layers
    return max(net_layers, int(math.ceil((height_mm + allowance_mm) / layer_mm - 1e-9)))


def fits(W: float, wd: Widths) -> bool:
    """Whether a thin feature W wide gets a legal bead layout (the verdict's own test)."""
    lay = layout(W, wd)
    if lay is None:
        return False
    if lay.n == 1:
        return W <= wd.hi / 0.97
    return lay.filled >= 0.97 * W


def stretch(W: float, wd: Widths, allowance_mm: float) -> float | None:
    """Near-net: the nearest width W' in [W, W + 2a] (a multiple of 0.05 mm over W) that a legal
    bead layout fills — the beads stand out of the grown region by at most `a` a side — or None."""
    if fits(W, wd):
        return W
    if allowance_mm <= 0.0:
        return None
    for k in range(1, int(2.0 * allowance_mm / STEP_MM + 1e-9) + 1):
        if fits(W + k * STEP_MM, wd):
            return W + k * STEP_MM
    return None


def stretched(piece: Polygon, W: float, wd: Widths, allowance_mm: float) -> tuple[Polygon, float] | None:
    """Near-net: a thin piece of the grown region too narrow for a legal bead layout (or between
    fits) widened by up to the allowance a side until one fills it, as (piece, width), or None."""
    if allowance_mm <= 0.0:
        return None
    W2 = stretch(W, wd, allowance_mm)
    if W2 is None:
        return None
    return piece.buffer(0.5 * (W2 - W), quad_segs=8), W2


def leaning_bead(piece: Polygon, island: Polygon, wd: Widths, allowance_mm: float) -> Path2D | None:
    """Near-net: one narrowest legal bead for a piece too narrow for it that leans on the rest of the
    island (a piece the thin/thick split cut off): along the piece's axis, moved where the bead stays
    within the allowance of the island; kept when it covers 90 % of the piece."""
    if allowance_mm <= 0.0:
        return None
    w = wd.lo
    room = island.buffer(allowance_mm - 0.49 * w, quad_segs=8)
    if room.is_empty:
        return None
    for axis in centre_lines(piece, w, depth=1):
        pts = np.array(axis.points, dtype=np.float64)
        out = ~shapely.contains_xy(room, pts[:, 0], pts[:, 1])
        if out.any():
            edge = room.boundary
            pts[out] = shapely.get_coordinates(shapely.line_interpolate_point(
                edge, shapely.line_locate_point(edge, shapely.points(pts[out]))))
        pts = pts[np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6]]
        if len(pts) < 2:
            continue
        fp = shapely.buffer(shapely.linestrings(pts), 0.5 * w, quad_segs=4)
        if float(piece.intersection(fp).area) >= 0.9 * piece.area:
            return Path2D("gap", pts, w, False, w, lone=True)
    return None


def allowance_for(W: float, wd: Widths, limit_mm: float, allowance_mm: float = 0.0) -> float | None:
    """The smallest extra allowance e (a multiple of 0.05 mm, at most `limit_mm`) that makes a feature
    W wide at allowance `a` buildable (W + 2e wide, stretched by up to a + e a side), or None."""
    for k in range(int(limit_mm / STEP_MM) + 1):
        e = k * STEP_MM
        ok = fits(W + 2.0 * e, wd) if allowance_mm <= 0.0 else stretch(W + 2.0 * e, wd, allowance_mm + e) is not None
        if ok:
            return round(e, 2)
    return None


def small_loop(island: Polygon, wd: Widths, allowance_mm: float, min_length: float) -> Path2D | None:
    """Near-net: one closed bead for an island too small for a bead of the minimum length, standing
    out of it by at most the allowance; the legal width whose loop covers the island best, or None."""
    if allowance_mm <= 0.0:
        return None
    best: tuple[float, Path2D] | None = None
    room = island.buffer(allowance_mm, quad_segs=8)
    for w in np.linspace(wd.lo, wd.hi, 5):
        core = room.buffer(-0.5 * w, quad_segs=8)
        if not isinstance(core, Polygon) or core.is_empty or core.exterior.length < min_length:
            continue
        ring = np.asarray(core.exterior.coords)[:, :2]
        fp = shapely.buffer(shapely.linestrings(ring), 0.5 * w, quad_segs=4)
        cov = float(island.intersection(fp).area) / island.area
        if best is None or cov > best[0] + 1e-9:
            best = (cov, Path2D("perimeter", ring, float(w), closed=True, share_mm=float(w)))
    return best[1] if best is not None and best[0] >= 0.9 else None


def side_stock(net: shapely.Geometry, footprint: shapely.Geometry, width: float) -> tuple[float, float] | None:
    """(min, max) distance from the net contour out to the beads' edge; negative: the beads stop short."""
    if net.is_empty or footprint.is_empty:
        return None
    pts = shapely.get_coordinates(shapely.segmentize(net.boundary, 0.5 * width))
    if len(pts) == 0:
        return None
    d = shapely.distance(shapely.points(pts), footprint.boundary)
    inside = shapely.contains_xy(footprint, pts[:, 0], pts[:, 1])
    sd = np.where(inside, d, -d)
    return float(sd.min()), float(sd.max())

"""Width from the process: bead count and widths for walls narrower than two step-overs.

A wall of width W gets n beads of one legal width w' (inside the material's envelope at the
layer height) whose centres are r·w' apart, r between the stable limit (Ding 2015: 2/3 for the
parabola) and the tangent model's d*/w: W = w' + (n − 1)·r·w'. The fewest beads win; among
the widths that fit, the one nearest the nominal width.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from planner.gapfill import centre_lines
from planner.path2d import Path2D
from planner.process import ENVELOPE_RTOL, wfs_for_current
from planner.process import inverse_arrays  # noqa: PLC2701  (the vectorised inverse, same model)
from planner.regions import polygons_of

if TYPE_CHECKING:  # annotations only: `cell plan` passes a remembered material (core.config_cache) and
    # never imports pydantic
    from core.material import Material

MAX_BEADS = 8


@dataclass(frozen=True)
class Widths:
    """Legal bead widths at the layer height, and the spacing band as ratios of the width."""

    lo: float
    hi: float
    nominal: float
    r_lo: float  # stable limit (centre distance / width)
    r_hi: float  # tangent model d*/w


@dataclass(frozen=True)
class Layout:
    n: int
    width: float
    spacing: float  # centre distance between neighbours (0 for one bead)
    filled: float  # width the beads fill: width + (n − 1)·spacing


def legal_widths(material: Material, height: float, nominal: float, r_hi: float, allow_outside: bool) -> Widths:
    """The interval of widths whose welding point is inside the envelope at this height."""
    r_lo = min(material.bead.min_step_over_ratio, r_hi)
    if allow_outside:
        return Widths(0.3 * nominal, 1.5 * nominal, nominal, r_lo, r_hi)
    ws = np.linspace(0.2 * nominal, 3.0 * nominal, 2801)
    cur, _ = inverse_arrays(material.ribeiro, ws, np.full_like(ws, height))
    k = material.ribeiro
    wfs = np.asarray(wfs_for_current(material, cur))
    tol_i, tol_v = ENVELOPE_RTOL * k.i_max_a, ENVELOPE_RTOL * k.wfs_max_m_min  # as envelope_violations
    ok = ((cur >= k.i_min_a - tol_i) & (cur <= k.i_max_a + tol_i)
          & (wfs >= k.wfs_min_m_min - tol_v) & (wfs <= k.wfs_max_m_min + tol_v))
    if not ok.any():
        return Widths(nominal, nominal, nominal, r_lo, r_hi)
    return Widths(float(ws[ok].min()), float(ws[ok].max()), nominal, r_lo, r_hi)


def layout(W: float, wd: Widths) -> Layout | None:
    """The fewest legal beads that fill a wall W wide; None when even one bead is too wide."""
    if W < wd.lo * (1 - 1e-6):
        return None
    for n in range(1, MAX_BEADS + 1):
        k = n - 1
        # w' ranges over [W/(1 + k·r_hi), W/(1 + k·r_lo)] for the spacing band, inside [lo, hi].
        a, b = max(W / (1 + k * wd.r_hi), wd.lo), min(W / (1 + k * wd.r_lo), wd.hi)
        # Keep 3 % off the stable limit when the band allows: a spacing right at it is one
        # rounding away from too close.
        if k and a <= b:
            b = max(a, min(b, W / (1 + k * wd.r_lo * 1.03)))
        if a <= b * (1 + 1e-9):
            w = float(np.clip(wd.nominal, a, b)) if n > 1 else float(np.clip(W, wd.lo, wd.hi))
            sp = (W - w) / k if k else 0.0
            return Layout(n, w, sp, W)
        if W / (1 + k * wd.r_lo) < wd.lo:  # more beads only get narrower: no fit
            break
    # Between fits (e.g. wider than one bead, narrower than two): the widest single bead, short of W.
    return Layout(1, wd.hi, 0.0, wd.hi)


def wall_width(piece: Polygon, tol: float) -> float:
    """Width of a thin piece: the diameter of its largest inscribed circle.

    A ring or a wall of even width W and length L has area L·W and perimeter 2(L + W): W is the
    small root of that pair (exact for a rectangle, to first order for a ring). The estimate
    stands when an inset of just under half of it leaves something and just over leaves nothing
    but junctions: the corner of an L or the crossing of a T bulges wider than the arms (an 8 mm
    L's corner holds a 9.4 mm circle), and a layout for the bulge would space the arms' loops
    apart (issue 29: two 3.95 mm loops 4.06 mm apart in the 8 mm legs, a crevice). Else the
    inscribed circle is searched (slow on large rings: its grid covers the hole too).
    """
    a, p = piece.area, piece.length
    ring = 2.0 * a / p  # exact for a concentric ring
    strip = (p - np.sqrt(max(p * p - 16.0 * a, 0.0))) / 4.0  # exact for a rectangle
    fine = 0.25 * tol
    for w0 in ((ring, strip) if len(piece.interiors) == 1 else (strip,)):
        if piece.buffer(-0.5 * w0 + fine, quad_segs=4).is_empty:
            continue
        over = piece.buffer(-0.5 * w0 - fine, quad_segs=4)
        # junctions only in a wall: at least two widths long (a blob, a disc, is not a wall)
        if over.is_empty or (a / w0 >= 2.0 * w0 and _junctions_only(over, w0)):
            return float(w0)
    return 2.0 * float(shapely.length(shapely.maximum_inscribed_circle(piece, tol)))


def _junctions_only(core: shapely.Geometry, w0: float) -> bool:
    """Is what a wall w0 wide leaves beyond half its width only junction bulges (or nothing)?
    Each piece left must be smaller than the wall is wide: a wall that widens along its length
    (a taper, a boss longer than the wall is wide) leaves a long piece and is measured by its
    inscribed circle instead."""
    for q in polygons_of(core):
        x0, y0, x1, y1 = q.bounds
        if max(x1 - x0, y1 - y0) > w0:
            return False
    return True


def _ring_centre(piece: Polygon, W: float) -> np.ndarray | None:
    """The centre line of an even ring (one hole) directly: its outer contour offset by W/2."""
    if len(piece.interiors) != 1:
        return None
    inner = Polygon(piece.exterior).buffer(-0.5 * W, quad_segs=8)
    if not isinstance(inner, Polygon) or inner.is_empty:
        return None
    pts = np.asarray(inner.exterior.coords)[:, :2]
    d = shapely.distance(shapely.points(pts), piece.boundary)
    if np.min(d) < 0.45 * W:  # uneven ring: the medial axis is needed
        return None
    return pts


def thin_beads(piece: Polygon, lay: Layout, lone_share: float, wd: Widths,
               wall: float) -> tuple[list[Path2D], list[float]]:
    """Beads for a thin piece: n//2 concentric loops, and a centre-line bead when n is odd.

    One bead (n = 1) follows the medial axis at the local width (twice the median inscribed
    radius along it, inside the legal widths): a junction's bulge does not widen every arm.
    `wall` is the piece's measured width. Returns the beads and the local widths no legal bead
    fills (for the verdict).
    """
    out: list[Path2D] = []
    w, d, n = lay.width, lay.spacing, lay.n
    share = lay.filled / n
    for k in range(n // 2):
        geom = piece.buffer(-(0.5 * w + k * d), quad_segs=6)
        for p in polygons_of(geom):
            if p.area <= 1e-6 * w * w:
                continue
            p = orient(p, 1.0)
            for ring in (p.exterior, *p.interiors):
                out.append(Path2D("perimeter", np.asarray(ring.coords)[:, :2], w, closed=True, share_mm=share))
    if n % 2 == 0:
        return out, []
    ring = _ring_centre(piece, lay.filled)
    if ring is not None:
        s = lone_share * w if n == 1 else share
        out.append(Path2D("gap", ring, w, True, s, lone=n == 1))
        return out, []
    if n > 1:
        # The middle bead only where the wall is as wide as the layout: elsewhere the loops meet.
        room = piece.buffer(-(0.5 * w + (n // 2 - 1) * d + 0.9 * d))
        if room.is_empty:
            return out, []
        out += [Path2D("gap", b.points, w, b.closed, share) for b in centre_lines(room.buffer(0.4 * d), wd.nominal, depth=1)]
        return out, []
    wide: list[float] = []
    for b in centre_lines(piece, wd.nominal, depth=3):
        # The axis's median radius runs a little short of an even wall's measured width: that wins.
        local = wall if abs(b.width_mm - wall) < 0.1 * wall else b.width_mm
        if local > wd.hi / 0.97:
            wide.append(local)
        wb = float(np.clip(local, wd.lo, wd.hi))
        out.append(Path2D("gap", b.points, wb, b.closed, lone_share * wb, lone=True))
    return out, wide

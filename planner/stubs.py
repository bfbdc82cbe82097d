"""No stubs: every pass at least `min_bead_length_mm` long, merged into a neighbour or reported."""
from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon

from planner.ordering import link_into_loops
from planner.path2d import Path2D


def clean(p: Path2D) -> Path2D | None:
    """Repeated points removed; None for a bead of no length (it would be a spot weld)."""
    pts = p.points
    keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6]
    pts = pts[keep]
    if len(pts) < 2 or (p.closed and len(pts) < 4):
        return None
    return Path2D(p.role, pts, p.width_mm, p.closed, p.share_mm, p.lone)


def no_stubs(groups: list[list[Path2D]], min_len: float, island: Polygon, layer: int,
             dropped: list[str], reach: float) -> list[list[Path2D]]:
    """Short beads joined to the nearest open bead within `reach` (through the island) or to a
    loop; else dropped and listed in `dropped` (layer, where, length)."""
    groups = [[c for c in (clean(p) for p in g) if c is not None] for g in groups]
    shapely.prepare(island)
    out = [list(g) for g in groups]
    for gi, g in enumerate(groups):
        for p in g:
            if p.length >= min_len:
                continue
            out[gi] = [q for q in out[gi] if q is not p]
            if _merge(p, out, island, reach):
                continue
            c = p.points.mean(axis=0)
            dropped.append(f"layer {layer}: {p.role} bead at ({c[0]:.1f}, {c[1]:.1f}) of {p.length:.1f} mm, "
                           f"shorter than {min_len:.1f} mm")
    return out


def _merge(stub: Path2D, groups: list[list[Path2D]], island: Polygon, reach: float) -> bool:
    """Weld the stub onto the nearest open bead end, or onto a loop (the arc runs on); in place."""
    best = _nearest_end(stub, groups, reach)
    if best is not None:
        gi, qi, q_end, s_end = best
        q = groups[gi][qi]
        a = q.reversed() if q_end == 0 else q  # a ends where the stub is
        b = stub if s_end == 0 else stub.reversed()
        if island.covers(shapely.linestrings([a.points[-1], b.points[0]])):
            groups[gi][qi] = Path2D(q.role, np.vstack([a.points, b.points]), q.width_mm, False, q.share_mm, q.lone)
            return True
    for gi, g in enumerate(groups):
        loops = [q for q in g if q.closed]
        if not loops:
            continue
        merged, rest = link_into_loops(loops, [stub], reach)
        if not rest:
            groups[gi] = [q for q in g if not q.closed] + merged
            return True
    return False


def _nearest_end(stub: Path2D, groups: list[list[Path2D]], reach: float) -> tuple[int, int, int, int] | None:
    """(group, bead, its end 0 or -1, the stub's end 0 or -1) of the open bead end nearest to one of
    the stub's ends within `reach`; the first in group, bead, end order among equals."""
    open_ = [(gi, qi) for gi, g in enumerate(groups) for qi, q in enumerate(g) if not q.closed]
    if not open_:
        return None
    ends = np.array([(groups[gi][qi].points[0], groups[gi][qi].points[-1]) for gi, qi in open_])  # (m, 2, 2)
    tips = np.array([stub.points[0], stub.points[-1]])
    diff = ends[:, :, None, :] - tips[None, None, :, :]   # (bead, its end, the stub's end, xy)
    d = np.hypot(diff[..., 0], diff[..., 1]).ravel()
    d = np.where(d <= reach, d, np.inf)
    k = int(np.argmin(d))
    if not np.isfinite(d[k]):
        return None
    b, q_end, s_end = k // 4, (k // 2) % 2, k % 2
    return open_[b][0], open_[b][1], -q_end, -s_end


def drop_short(paths: list[Path2D], min_len: float, layer: int, dropped: list[str]) -> list[Path2D]:
    """The last guard: a pass still shorter than the minimum (whatever made it) is dropped and named."""
    keep = []
    for p in paths:
        if p.length >= min_len - 1e-9:
            keep.append(p)
            continue
        c = p.points.mean(axis=0)
        dropped.append(f"layer {layer}: {p.role} bead at ({c[0]:.1f}, {c[1]:.1f}) of {p.length:.1f} mm, "
                       f"shorter than {min_len:.1f} mm")
    return keep

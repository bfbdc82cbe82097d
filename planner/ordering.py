"""Seams, linking infill into perimeter loops, and bead order (nearest neighbour) within a layer."""
from __future__ import annotations

from typing import Any

import math

import numpy as np
import shapely

from planner.path2d import Path2D

GOLDEN_DEG = 137.50776405  # seam angle advance per layer: seams never line up over a few layers


def seam_at(loop: Path2D, layer_index: int) -> Path2D:
    """Rotate a closed loop to start at the vertex facing this layer's seam direction."""
    pts = loop.points[:-1]
    c = pts.mean(axis=0)
    a = math.radians((layer_index * GOLDEN_DEG) % 360.0)
    score = (pts - c) @ np.array([math.cos(a), math.sin(a)])
    return _rotate(loop, int(np.argmax(score)))


def _rotate(loop: Path2D, i: int) -> Path2D:
    pts = loop.points[:-1]
    p = np.roll(pts, -i, axis=0)
    return Path2D(loop.role, np.vstack([p, p[:1]]), loop.width_mm, True, loop.share_mm, loop.lone)


def _split_at(loop: Path2D, q: np.ndarray) -> Path2D:
    """Loop re-seamed at its point nearest q (a vertex is inserted there)."""
    pts = loop.points
    a, b = pts[:-1], pts[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", q - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18), 0, 1)
    proj = a + t[:, None] * ab
    i = int(np.argmin(np.linalg.norm(proj - q, axis=1)))
    ring = np.vstack([proj[i], pts[i + 1:-1], pts[:i + 1], proj[i]])
    keep = np.r_[True, np.linalg.norm(np.diff(ring, axis=0), axis=1) > 1e-9]
    return Path2D(loop.role, ring[keep], loop.width_mm, True, loop.share_mm, loop.lone)


def _dist_to_loop(loop: Path2D, q: np.ndarray) -> float:
    a, b = loop.points[:-1], loop.points[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", q - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - q, axis=1)))


def link_into_loops(loops: list[Path2D], chains: list[Path2D], reach: float) -> tuple[list[Path2D], list[Path2D]]:
    """Continue an innermost perimeter loop into an infill chain that starts within `reach`.

    The arc then runs around the loop, steps over to the chain and fills it: one arc start less.
    Returns (merged passes, chains left alone).
    """
    loops = list(loops)
    used = [False] * len(loops)
    merged: list[Path2D] = []
    rest: list[Path2D] = []
    for ch in chains:
        best = None
        for li, lp in enumerate(loops):
            if used[li] or lp.points.shape[0] < 4:
                continue
            for rev in (False, True):
                end = ch.points[-1] if rev else ch.points[0]
                d = _dist_to_loop(lp, end)
                if d <= reach and (best is None or d < best[0]):
                    best = (d, li, rev)
        if best is None:
            rest.append(ch)
            continue
        _, li, rev = best
        used[li] = True
        c = ch.reversed() if rev else ch
        lp = _split_at(loops[li], c.points[0])
        merged.append(Path2D("perimeter", np.vstack([lp.points, c.points]), lp.width_mm, False, lp.share_mm, lp.lone))
    merged_loops = [lp for lp, u in zip(loops, used) if not u]
    return merged_loops + merged, rest


def order_passes(groups: list[list[Path2D]], start: np.ndarray) -> tuple[list[Path2D], np.ndarray]:
    """Greedy nearest-neighbour order, group after group; open beads may run either way."""
    out: list[Path2D] = []
    pos = np.asarray(start, dtype=float)
    for group in groups:
        todo = list(group)
        while todo:
            best_i, best_d, best_rev = 0, np.inf, False
            for i, p in enumerate(todo):
                d0 = float(np.hypot(*(p.points[0] - pos)))
                if d0 < best_d:
                    best_i, best_d, best_rev = i, d0, False
                if not p.closed:
                    d1 = float(np.hypot(*(p.points[-1] - pos)))
                    if d1 < best_d:
                        best_i, best_d, best_rev = i, d1, True
            p = todo.pop(best_i)
            p = p.reversed() if best_rev else p
            out.append(p)
            pos = p.points[-1]
    return out, pos


def _closest_ends(chains: list[Path2D], tags: list[int], rejected: set[tuple[int, int, bool, bool]],
                  reach: float) -> tuple[float, int, int, bool, bool] | None:
    """The nearest (end of a, start of b) pair within reach not refused yet: (d, i, j, ra, rb);
    the first in (i, j, ra, rb) order among equals."""
    first = np.array([c.points[0] for c in chains])
    last = np.array([c.points[-1] for c in chains])
    pa = np.stack([last, first], axis=1)  # [i, ra]: where a ends when run forward / reversed
    pb = np.stack([first, last], axis=1)  # [j, rb]: where b starts
    d = np.linalg.norm(pa[:, None, :, None, :] - pb[None, :, None, :, :], axis=-1)  # [i, j, ra, rb]
    n = len(chains)
    d[np.arange(n), np.arange(n)] = np.inf
    index = {t: k for k, t in enumerate(tags)}
    for ti, tj, rev_a, rev_b in rejected:
        if ti in index and tj in index:
            d[index[ti], index[tj], int(rev_a), int(rev_b)] = np.inf
    k = int(np.argmin(d))
    i, j, ra, rb = np.unravel_index(k, d.shape)
    best = float(d[i, j, ra, rb])
    if not best <= reach:
        return None
    return best, int(i), int(j), bool(ra), bool(rb)


def join_chains(chains: list[Path2D], reach: float, corridor: Any) -> list[Path2D]:
    """Join open beads whose ends lie within `reach` through `corridor`: fewer arc starts."""
    chains = list(chains)
    tags = list(range(len(chains)))  # stable names for pairs already refused (never id())
    serial = len(chains)
    shapely.prepare(corridor)
    rejected: set[tuple[int, int, bool, bool]] = set()
    while len(chains) > 1:
        best = _closest_ends(chains, tags, rejected, reach)
        if best is None:
            break
        _, i, j, ra, rb = best
        a = chains[i].reversed() if ra else chains[i]
        b = chains[j].reversed() if rb else chains[j]
        if not corridor.covers(shapely.linestrings([a.points[-1], b.points[0]])):
            rejected.add((tags[i], tags[j], ra, rb))  # the step would leave the region
            continue
        joined = Path2D(a.role, np.vstack([a.points, b.points]), a.width_mm, False, a.share_mm)
        chains = [c for k, c in enumerate(chains) if k not in (i, j)] + [joined]
        tags = [t for k, t in enumerate(tags) if k not in (i, j)] + [serial]
        serial += 1
    return chains

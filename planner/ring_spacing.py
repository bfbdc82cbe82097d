"""Rings of one offset level kept at Ding's spacing (docs/along-the-path.md "Ring spacing").

Offsetting a region with a hole gives, at each level, one ring round the outside and one round the
hole. Where the region narrows (the middle of a square's sides around a round hole), the two rings
of a level can run much closer than the stable limit (`min_step_over_ratio` × width): on the demo
part the square's inner ring and the hole's outer ring run 0.2 mm apart there, two beads on one
line. Each lays its share, but the later one lands on the earlier one's flank, and no speed levels
that (the metal is laid on the same line twice).

Such a pair keeps one ring whole and trims the other where it runs closer than `cut_mm` to it: the
trimmed ring becomes open beads (the parts of it that keep their distance), and a piece shorter than
the shortest bead is dropped. The perimeters cut at `END_REACH` × the width, not at Ding's step-over:
past the point where the trimmed ring is a step-over from the kept one, the region between the kept
ring and the level outside narrows to a wedge that no bead covered (the demo's true top sank there
about 0.07 mm a layer). A piece's end runs on into it along the wedge's middle: where the trimmed
ring comes within `beyond_mm` (its distance to the level outside it) of the kept ring, its centre
moves out to halfway between the two, and it ends where that middle is `cut_mm` from each.
Which ring is trimmed: the choice that keeps the
more bead length (the other ring whole plus the trimmed ring's pieces long enough to weld); on the
demo the square's inner ring becomes four corner beads and the hole's ring stays closed.

Pure: Path2D in, Path2D out; deterministic.
"""
from __future__ import annotations

import numpy as np
import shapely

from planner.path2d import Path2D

SAMPLE_MM = 0.5   # a ring is judged (and trimmed) on points this far apart
# where a trimmed ring's piece ends: its centre this share of the width from the kept ring's and from
# the ring outside it (docs/along-the-path.md "Corner beads' ends run on into the wedge")
END_REACH = 0.55


def spaced(loops: list[Path2D], min_spacing: float, cut_mm: float, min_length: float,
           beyond_mm: float | None = None) -> list[Path2D]:
    """The level's loops, a ring trimmed wherever it runs closer than `min_spacing` to another one
    of the level (cut back to `cut_mm`); loops that keep their distance are returned as they are.
    `beyond_mm`: how far the level outside lies from each ring of this one (None: nothing outside,
    the trimmed ring's ends stay on its line)."""
    if len(loops) < 2:
        return loops
    out = list(loops)
    settled: set[tuple[int, int]] = set()   # (piece, kept ring) already trimmed to each other (ids)
    for _ in range(len(loops)):   # each round trims one ring of the worst pair left
        pair = _closest_pair(out, min_spacing, settled)
        if pair is None:
            break
        i, j = pair
        # trim the ring whose giving way keeps the more bead length (the first of the pair on a tie)
        trim, (_, pieces) = max(((t, _kept(out, t, k, cut_mm, min_length, beyond_mm)) for t, k in ((i, j), (j, i))),
                                key=lambda o: (o[1][0], -o[0]))
        keep = out[j if trim == i else i]
        settled |= {(id(q), id(keep)) for q in pieces}
        out = out[:trim] + pieces + out[trim + 1:]
    return out


def _closest_pair(loops: list[Path2D], min_spacing: float, settled: set[tuple[int, int]]) -> tuple[int, int] | None:
    """The two loops that run closer than `min_spacing` over the longest stretch (None: none do); a
    piece already trimmed to its ring (`settled`, a pair of ids either way round) is no pair again."""
    lines = [shapely.linestrings(p.points) for p in loops]
    best: tuple[float, int, int] | None = None
    for i, p in enumerate(loops):
        pts = _samples(p)
        for j in range(i + 1, len(loops)):
            if (id(p), id(loops[j])) in settled or (id(loops[j]), id(p)) in settled:
                continue
            if shapely.distance(lines[i], lines[j]) >= min_spacing:
                continue
            close = float(np.count_nonzero(shapely.distance(shapely.points(pts), lines[j]) < min_spacing))
            if close > 0 and (best is None or close > best[0]):
                best = (close, i, j)
    return None if best is None else (best[1], best[2])


def _samples(p: Path2D) -> np.ndarray:
    """The bead's centre line every SAMPLE_MM or less (a closed loop without its repeated end)."""
    line = shapely.segmentize(shapely.linestrings(p.points), SAMPLE_MM)
    pts: np.ndarray = shapely.get_coordinates(line)
    return pts[:-1] if p.closed and len(pts) > 1 else pts


def _kept(loops: list[Path2D], trim: int, keep: int, cut_mm: float, min_length: float,
          beyond_mm: float | None) -> tuple[float, list[Path2D]]:
    """(bead length kept, the trimmed ring's pieces) when ring `trim` gives way to ring `keep`."""
    p = loops[trim]
    pts = _samples(p)
    points, kept_line = shapely.points(pts), shapely.linestrings(loops[keep].points)
    d = shapely.distance(points, kept_line)
    if beyond_mm is not None:   # within `beyond_mm` of the kept ring: halfway between it and the level outside
        nearest = shapely.get_coordinates(shapely.shortest_line(points, kept_line))[1::2]
        move = np.clip(beyond_mm - d, 0.0, None) / 2.0
        pts = pts + (pts - nearest) / np.maximum(d, 1e-9)[:, None] * move[:, None]
        d = d + move
    far = d >= cut_mm
    pieces = [Path2D(p.role, _simplified(run), p.width_mm, False, p.share_mm, p.lone)
              for run in _runs(pts, far, p.closed)]
    pieces = [q for q in pieces if q.length >= min_length]
    if len(pieces) == 1 and bool(far.all()):
        pieces = [p]
    return loops[keep].length + sum(q.length for q in pieces), pieces


def _runs(pts: np.ndarray, keep: np.ndarray, closed: bool) -> list[np.ndarray]:
    """The stretches of consecutive kept points (a closed ring's run may wrap round its start)."""
    if keep.all():
        return [np.vstack([pts, pts[:1]]) if closed else pts]
    if closed:   # start the walk at a dropped point: no run wraps round
        k = int(np.flatnonzero(~keep)[0])
        pts, keep = np.roll(pts, -k, axis=0), np.roll(keep, -k)
    edges = np.diff(np.r_[0, keep.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [pts[a:b] for a, b in zip(starts, ends) if b - a >= 2]


def _simplified(pts: np.ndarray) -> np.ndarray:
    """The sampled run with its collinear points taken out (its corners kept)."""
    line = shapely.simplify(shapely.linestrings(pts), 0.01)
    return np.asarray(shapely.get_coordinates(line))

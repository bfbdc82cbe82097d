"""Ding's closeness check searches pieces of the centre lines (planner/ding.py): the share is the
one measured bead against bead."""
from __future__ import annotations

import numpy as np
import shapely

from planner.ding import close_share
from planner.path2d import Path2D


def _by_bead(paths: list[Path2D], ratio: float, width: float) -> float:
    """The share measured the plain way: every sample against every other whole bead."""
    lines = [shapely.linestrings(p.points) for p in paths]
    close = total = 0
    for i, ln in enumerate(lines):
        k = max(1, int(np.floor(shapely.length(ln) / (0.5 * width))))
        pts = shapely.line_interpolate_point(ln, (np.arange(k) + 0.5) / k, normalized=True)
        d = np.array([shapely.distance(pts, other) for j, other in enumerate(lines) if j != i])
        # close to any other bead, not at a junction with it (a bead end meeting another)
        close += int(np.sum(np.any((d < 0.98 * ratio * paths[i].width_mm) & (d > 0.25 * width), axis=0)))
        total += k
    return close / total


def _layer() -> list[Path2D]:
    """A zigzag of 12 rows inside a loop, rows crowding at one end, and a short gap bead."""
    rows = []
    for r in range(12):
        y = r * (3.0 + 0.15 * r)
        xs = (0.0, 60.0) if r % 2 == 0 else (60.0, 0.0)
        rows += [(x, y + 0.4 * np.sin(x / 7.0)) for x in np.linspace(*xs, 25)]
    t = np.linspace(0.0, 2 * np.pi, 90)
    loop = np.column_stack([30 + 36 * np.cos(t), 22 + 30 * np.sin(t)])
    return [Path2D("infill", np.array(rows), 4.0), Path2D("perimeter", loop, 4.0, closed=True),
            Path2D("gap", np.array([[2.0, 1.5], [6.0, 1.9]]), 3.0)]


def test_the_share_is_the_bead_by_bead_one():
    paths = _layer()
    for ratio in (0.6, 0.738, 0.9):
        got = close_share(paths, ratio, 4.0)
        assert got == _by_bead(paths, ratio, 4.0)
    assert 0.05 < close_share(paths, 0.738, 4.0) < 0.95

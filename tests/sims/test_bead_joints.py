"""A bead is one pool from its arc start to its arc end (issue 35, docs/process-physics.md): the
moves it is laid in leave no trace in the world's height map, a turn's outside is covered, and
the metal of a bead's first and last pool (two bead widths) levels out with its round start and end."""
from __future__ import annotations

import numpy as np
import pytest

from sims.heightmap import HeightMap

W, AREA = 7.0, 5.0


def _bead(hm: HeightMap, pts: list[tuple[float, float]], move_mm: float) -> None:
    """One bead along a polyline, laid in moves of about `move_mm` (the arc on the whole way)."""
    hm.new_bead()
    for (x0, y0), (x1, y1) in zip(pts, pts[1:]):
        n = max(1, int(round(float(np.hypot(x1 - x0, y1 - y0)) / move_mm)))
        for i in range(n):
            a, b = i / n, (i + 1) / n
            hm.lay((x0 + (x1 - x0) * a, y0 + (y1 - y0) * a), (x0 + (x1 - x0) * b, y0 + (y1 - y0) * b), W, AREA)
    hm.end_bead()


def _wall(move_mm: float, layers: int = 8) -> HeightMap:
    hm = HeightMap(0.5)
    for la in range(layers):
        _bead(hm, [(0.0, 0.0), (60.0, 0.0)] if la % 2 == 0 else [(60.0, 0.0), (0.0, 0.0)], move_mm)
    return hm


def test_a_wall_laid_in_short_moves_is_the_wall_laid_in_one():
    # The plan's moves are 3.44-3.5 mm, the same points every layer. Each move poured a round end and
    # a round start again and its metal on the 6 or 7 rows of cells it covered: the middle of a
    # wall spread 0.66-2.72 mm after 12 layers, which no controller could see or level.
    one, short = _wall(60.0), _wall(60.0 / 17)
    xs = np.arange(17.0, 43.0, 0.25) + 0.1     # past the ends' pools (two bead widths and the round end)
    top_one = one.deposit_tops(xs, np.full(xs.size, 0.1))
    top_short = short.deposit_tops(xs, np.full(xs.size, 0.1))
    assert np.ptp(top_short) < 0.1                       # the middle stands level
    assert np.max(np.abs(top_short - top_one)) < 0.1     # as if laid in one move
    assert short.volume_mm3 == pytest.approx(8 * 60.0 * AREA, rel=0.01)   # the wire's metal, all of it


def test_a_turn_covers_its_outside_and_keeps_the_metal():
    hm = HeightMap(0.5)
    _bead(hm, [(0.0, 0.0), (30.0, 0.0), (30.0, 30.0)], 2.5)
    assert hm.volume_mm3 == pytest.approx(60.0 * AREA, rel=0.01)
    mid = hm.surface(15.1, 0.1)
    outside = hm.surface(32.1, -2.1)                     # the corner's outside, beyond both strips
    assert outside > 0.1 * mid                           # the pool swept round the corner: no notch
    assert hm.surface(30.1, 15.1) == pytest.approx(mid, rel=0.05)   # the second leg as the first


def test_a_beads_ends_level_its_last_width_with_its_round_end():
    hm = HeightMap(0.5)
    _bead(hm, [(0.0, 0.0), (40.0, 0.0)], 3.5)
    mid = hm.surface(20.1, 0.1)
    end = [hm.surface(x, 0.1) for x in np.arange(26.6, 40.0, 0.5)]
    beyond = hm.surface(41.1, 0.1)
    # the pool's (two bead widths') metal spread over it and the round end: one level, lower than the middle
    assert np.ptp(end) < 0.02 and 0.65 * mid < end[0] < 0.9 * mid
    assert beyond == pytest.approx(end[0], abs=0.02)
    start = [hm.surface(x, 0.1) for x in np.arange(0.1, 13.5, 0.5)]
    assert np.ptp(start) < 0.02 and 0.65 * mid < start[0] < 0.9 * mid

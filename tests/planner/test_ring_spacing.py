"""Rings of one offset level kept at Ding's spacing (docs/along-the-path.md "Ring spacing"): the demo
part's square ring no longer runs on the hole's ring where the region narrows."""
from __future__ import annotations

import numpy as np
import shapely

from controller.defaults import DEMO_PART, DEMO_WIDTH_MM
from core.config import load_material
from planner.path2d import Path2D
from planner.options import PlanOptions
from planner.plan import plan_part
from planner.ring_spacing import END_REACH, spaced

MAT = load_material("inconel718-1.0mm")


def _square(c: float, half: float) -> np.ndarray:
    return np.array([[c - half, c - half], [c + half, c - half], [c + half, c + half], [c - half, c + half],
                     [c - half, c - half]])


def _circle(c: float, r: float, n: int = 128) -> np.ndarray:
    a = np.linspace(0.0, 2 * np.pi, n + 1)
    return np.column_stack([c + r * np.cos(a), c + r * np.sin(a)])


def _closest(paths: list[Path2D]) -> float:
    """The least distance from any bead's centre line (every 0.5 mm) to another bead's."""
    lines = [shapely.linestrings(p.points[:, :2]) for p in paths]
    out = np.inf
    for i, line_i in enumerate(lines):
        pts = shapely.get_coordinates(shapely.segmentize(line_i, 0.5))
        for j, line in enumerate(lines):
            if j != i:
                out = min(out, float(shapely.distance(shapely.points(pts), line).min()))
    return out


def test_a_square_ring_that_runs_on_a_round_ring_gives_way_in_corner_beads() -> None:
    # the demo part's second level: the square's ring 0.2 mm from the hole's at each side's middle
    square = Path2D("perimeter", _square(35.0, 26.33), 7.0, closed=True, share_mm=5.17)
    circle = Path2D("perimeter", _circle(35.0, 26.14), 7.0, closed=True, share_mm=5.17)
    assert _closest([square, circle]) < 0.3
    out = spaced([square, circle], 0.667 * 7.0, 5.17, 14.0)
    kept = [p for p in out if p.closed]
    corners = [p for p in out if not p.closed]
    assert len(kept) == 1 and kept[0] is circle           # the hole's ring stays whole
    assert len(corners) == 4 and all(p.length >= 14.0 for p in corners)
    assert _closest(out) >= 5.17 - 0.5                    # Ding's step-over, to the sampling
    # each corner bead runs round its own corner of the square
    ends = sorted((round(float(p.points[:, 0].mean())), round(float(p.points[:, 1].mean()))) for p in corners)
    assert ends == sorted({(x, y) for x in (ends[0][0], ends[-1][0]) for y in (ends[0][1], ends[-1][1])})


def test_corner_beads_run_on_into_the_wedge_and_are_trimmed_once() -> None:
    # cut closer than the stable limit (the perimeters' END_REACH): the corner beads' ends run on past
    # Ding's step-over into the wedge between the rings, and a piece is not taken for a new close pair
    square = Path2D("perimeter", _square(35.0, 26.33), 7.0, closed=True, share_mm=5.17)
    circle = Path2D("perimeter", _circle(35.0, 26.14), 7.0, closed=True, share_mm=5.17)
    at_step = [p for p in spaced([square, circle], 0.667 * 7.0, 5.17, 14.0) if not p.closed]
    out = spaced([square, circle], 0.667 * 7.0, END_REACH * 7.0, 14.0)
    corners = [p for p in out if not p.closed]
    assert len(out) == 5 and len(corners) == 4
    assert all(p.length > q.length + 4.0 for p, q in zip(corners, at_step))   # 2 mm and more at each end
    assert END_REACH * 7.0 - 0.5 <= _closest(out) < 0.667 * 7.0
    # with the level outside a step away, the ends run on along the wedge's middle, bending out to it
    bent = [p for p in spaced([square, circle], 0.667 * 7.0, END_REACH * 7.0, 14.0, beyond_mm=5.17) if not p.closed]
    assert len(bent) == 4 and all(p.length > q.length + 4.0 for p, q in zip(bent, corners))
    outer = shapely.linestrings(_square(35.0, 26.33 + 5.17))
    kept_line = shapely.linestrings(circle.points)
    for p in bent:
        for end in (p.points[0], p.points[-1]):
            to_circle, to_outer = shapely.distance(shapely.points(end), kept_line), shapely.distance(shapely.points(end), outer)
            assert abs(to_circle - to_outer) < 0.3 and to_circle >= END_REACH * 7.0 - 0.3   # halfway, no closer


def test_rings_that_keep_their_distance_are_left_as_they_are() -> None:
    outer = Path2D("perimeter", _square(35.0, 31.5), 7.0, closed=True)
    inner = Path2D("perimeter", _square(35.0, 26.33), 7.0, closed=True)
    out = spaced([outer, inner], 0.667 * 7.0, 5.17, 14.0)
    assert out[0] is outer and out[1] is inner


def test_the_demo_parts_beads_keep_dings_spacing_and_each_lays_its_share() -> None:
    job = plan_part(str(DEMO_PART), PlanOptions(width_mm=DEMO_WIDTH_MM, perimeters="all", feed_forward=False), MAT)
    s = job.summary
    layer = job.layers[0]
    paths = [Path2D(p.role, p.points[:, :2], p.width_mm) for p in layer.passes]
    # no two beads on one line any more (it was 0.2 mm at each side's middle): only the corner beads'
    # ends come closer than the stable limit, and no closer than END_REACH of a width (to either side)
    assert _closest(paths) > END_REACH * DEMO_WIDTH_MM * 0.98
    assert s["mass_balance_max_error"] <= 0.03 and s["mass_balance_layer_max"] <= 0.03
    # the corner beads' last 5 mm at each end are the close neighbours (0.149 with two beads on one line)
    assert s["coverage_min"] >= 0.98 and s["close_neighbour_max"] <= 0.2

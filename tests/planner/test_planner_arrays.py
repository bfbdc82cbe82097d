"""The planner's array shortcuts (issue 28 item 7) give what the slower ways they replace give:
the mass balance's cell areas against GEOS overlays, its graded sample points on their beads at
the spacing they promise, the STL weld against a plain sort of the coordinates."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
from shapely.geometry import Point, box

from planner.balance import _first_of_each, graded_points
from planner.cellclip import cell_areas_inside
from planner.mesh import _stable_order, _weld, _weld_exact


def _cells(pts: np.ndarray) -> np.ndarray:
    cells = shapely.get_parts(shapely.voronoi_polygons(shapely.multipoints(pts), ordered=True,
                                                       extend_to=box(-40, -40, 60, 60)))
    bad = ~shapely.is_valid(cells)
    cells[bad] = shapely.make_valid(cells[bad])
    return cells


_rng = np.random.default_rng(28)
_t = np.linspace(0, 20, 121)
_a = np.linspace(0, 2 * np.pi, 200, endpoint=False)
POINTS = {
    "random": _rng.random((400, 2)) * 20,
    "grid (co-circular)": np.stack(np.meshgrid(np.arange(0, 20.0), np.arange(0, 20.0)), -1).reshape(-1, 2),
    "quarter-mm lattice": np.unique(np.round(_rng.random((400, 2)) * 80) / 4, axis=0),
    "bead rows": np.vstack([np.c_[_t, np.full_like(_t, y)] for y in (3, 7.4, 11.8, 16.2)]),
    "bead rings": np.vstack([np.c_[10 + r * np.cos(_a), 10 + r * np.sin(_a)] for r in (3, 5, 7)]),
}
ISLANDS = {
    "box with a hole": box(2, 1.5, 17, 15).difference(box(6, 6, 10, 9)),
    "ring": Point(10, 10).buffer(8.5, quad_segs=7).difference(Point(10.4, 10).buffer(2)),
    "star": shapely.Polygon(np.c_[10 + 8 * np.cos(_a[::25]) * (1 - 0.6 * (np.arange(8) % 2)),
                                  10 + 8 * np.sin(_a[::25]) * (1 - 0.6 * (np.arange(8) % 2))]),
    "box on the grid": box(3, 3, 15, 15),
}


@pytest.mark.parametrize("points", sorted(POINTS))
@pytest.mark.parametrize("island", sorted(ISLANDS))
def test_cell_areas_inside_an_island_are_geos_overlays(points, island):
    """Every cell the arrays decide has GEOS's area inside the island (to 1e-9 of a cell); the
    ones they cannot (a corner on the island's edge) are handed back, never guessed."""
    cells, poly = _cells(POINTS[points]), ISLANDS[island]
    edge = cells[~shapely.contains(poly, cells)]
    area, rest = cell_areas_inside(edge, poly)
    geos = np.asarray(shapely.area(shapely.intersection(edge, poly)))
    done = np.setdiff1d(np.arange(len(edge)), rest)
    assert len(done) >= 0.5 * len(edge)
    assert np.max(np.abs(area[done] - geos[done])) <= 1e-9 * max(1.0, float(np.max(geos)))


def test_cells_outside_inside_and_degenerate():
    """A cell wholly outside has nothing inside; one wholly inside its whole area; an empty or a
    non-polygon cell is handed back."""
    poly = box(0, 0, 10, 10)
    cells = np.array([box(20, 20, 21, 21), box(2, 2, 3, 4), box(9, 9, 11, 11), shapely.Polygon(),
                      shapely.MultiPolygon([box(1, 1, 2, 2), box(3, 3, 4, 4)])], dtype=object)
    area, rest = cell_areas_inside(cells, poly)
    assert area[0] == 0.0 and area[1] == pytest.approx(2.0)
    assert 2 in rest or area[2] == pytest.approx(1.0)  # its corner (10, 10) on the box's corner
    assert {3, 4} <= set(rest.tolist())


def test_graded_samples_lie_on_their_bead_hold_every_vertex_and_keep_their_spacing():
    """Every vertex is a sample; samples run along each bead in order, no two further apart than
    the coarse spacing, and no further than the fine one within `near` of a vertex."""
    rng = np.random.default_rng(7)
    fine, coarse, near = 0.5, 1.5, 1.5
    for trial in range(40):
        xys = []
        for _ in range(int(rng.integers(1, 4))):
            n = int(rng.integers(2, 30))
            step = np.column_stack([np.abs(rng.normal(size=n)), rng.normal(size=n)]) * rng.uniform(0.05, 8.0)
            xy = np.cumsum(step, axis=0) + rng.uniform(-100, 100, 2)  # x grows: the bead never crosses itself
            if trial % 5 == 0:
                k = int(rng.integers(1, n))
                xy[k] = xy[k - 1]  # a repeated corner: a segment of length 0
            xys.append(xy)
        pts, owner = graded_points(xys, fine, coarse, near)
        for i, xy in enumerate(xys):
            mine = pts[owner == i]
            line = shapely.linestrings(xy)
            assert np.all(shapely.distance(shapely.points(mine), line) < 1e-9)
            for v in xy:  # every vertex, exactly
                assert np.any(np.all(mine == v, axis=1))
            along = shapely.line_locate_point(line, shapely.points(mine))
            assert np.all(np.diff(along) >= -1e-9)  # in order along the bead
            gaps = np.diff(along)
            assert gaps.max(initial=0.0) <= coarse + 1e-9
            # near a vertex (by arc length) the gaps are the fine ones
            corner = np.r_[0.0, np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]
            mid = 0.5 * (along[1:] + along[:-1])
            close = np.min(np.abs(mid[:, None] - corner[None, :]), axis=1) < near - fine
            assert np.all(gaps[close] <= fine + 1e-9)


def test_junction_points_kept_once_as_numpy_unique_keeps_them():
    rng = np.random.default_rng(3)
    for trial in range(200):
        cells = np.round(rng.normal(size=(int(rng.integers(1, 300)), 2)) * rng.choice([0.5, 3.0, 100.0, 1e5]))
        if trial % 3 == 0:
            cells[int(rng.integers(0, len(cells)))] = -0.0
        _, first = np.unique(cells, axis=0, return_index=True)
        assert np.array_equal(_first_of_each(cells), np.sort(first))


def test_stable_order_is_a_stable_argsort_even_when_the_high_bits_tie():
    """The sort keeps only the hash's high bits above the index: hashes differing only in the low
    bits are put back in full-hash order."""
    rng = np.random.default_rng(5)
    n = 1000
    shift = (n - 1).bit_length()
    high = rng.integers(0, 20, n).astype(np.uint64) << np.uint64(40)
    h = high | rng.integers(0, 1 << shift, n).astype(np.uint64)  # many ties in the high bits
    order, sh = _stable_order(h)
    assert np.array_equal(order, np.argsort(h, kind="stable"))
    assert np.array_equal(sh, h[order])


def test_stl_weld_shares_exactly_equal_corners_as_a_sort_of_the_coordinates_does():
    rng = np.random.default_rng(11)
    corners = np.round(rng.normal(size=(300, 3)) * 10, 1).astype(np.float32)
    corners[::7] = -0.0  # -0.0 and 0.0 are one corner
    tri = corners[rng.integers(0, len(corners), (2000, 3))]
    v, f = _weld(tri)
    ve, fe = _weld_exact(np.ascontiguousarray(tri.reshape(-1, 3)) + np.float32(0.0))
    assert len(v) == len(ve) == len(np.unique(tri.reshape(-1, 3) + np.float32(0.0), axis=0))
    assert np.array_equal(v[f], ve[fe]) and np.array_equal(v[f], tri.astype(np.float64) + 0.0)

"""Mass balance per bead (issue 28 item 3, docs/contract.md §3.7): every pass lays the section it fills.

Measured from the job (wire area × WFS / speed × length) against the part's own section, and per
bead class against an independent partition of the section (each sample point to its nearest
bead centre line, a finer grid than the planner's)."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Point, box

from core.config import load_material
from planner.balance import partition_shares
from planner.extrude import extrude
from planner.path2d import Path2D
from planner.plan import PlanOptions, plan_part

MAT = load_material("inconel718-1.0mm")
WIRE = np.pi * MAT.wire_diameter_mm ** 2 / 4


def _laid(p) -> float:
    return WIRE * p.wfs_m_min * 1000.0 / p.speed_mm_min * p.length_mm


def _class_areas(section, layer, grid: float) -> dict[str, float]:
    """Area of the section nearest to each bead class's centre lines."""
    # a grid turned 0.3 rad off the axes: straight beads along x or y do not alias with its rows
    c, s_ = np.cos(0.3), np.sin(0.3)
    cx, cy = section.centroid.x, section.centroid.y
    r = float(np.hypot(section.bounds[2] - section.bounds[0], section.bounds[3] - section.bounds[1])) / 2 + grid
    u, v = np.meshgrid(np.arange(-r, r, grid), np.arange(-r, r, grid))
    x, y = cx + c * u.ravel() - s_ * v.ravel(), cy + s_ * u.ravel() + c * v.ravel()
    ok = shapely.contains_xy(section, x, y)
    pts = shapely.points(np.column_stack([x[ok], y[ok]]))
    lines = np.array([shapely.linestrings(p.points[:, :2]) for p in layer.passes], dtype=object)
    d = np.stack([shapely.distance(pts, ln) for ln in lines])
    near = np.argmin(d, axis=0)
    out: dict[str, float] = {}
    for i, p in enumerate(layer.passes):
        out[p.role] = out.get(p.role, 0.0) + float(np.sum(near == i)) / len(near) * section.area
    return out


def test_single_bead_wall_lays_the_wall_not_two_thirds_of_it():
    """The issue's wall: 80 x 5.2 x 10 mm at 6 mm beads laid 2,566 of 4,160 mm3 (-38 %)."""
    job = plan_part(extrude(box(0, 0, 80, 5.2), 10.0), PlanOptions(width_mm=6.0), MAT)
    h = job.layers[0].height_mm
    for layer in job.layers:
        assert len(layer.passes) == 1 and layer.passes[0].role == "gap"
        laid = sum(_laid(p) for p in layer.passes)
        assert laid == pytest.approx(80 * 5.2 * h, rel=0.03)
    total = sum(_laid(p) for L in job.layers for p in L.passes)
    assert total == pytest.approx(80 * 5.2 * h * len(job.layers), rel=0.03)
    assert job.summary["mass_balance_layer_max"] <= 0.03


@pytest.mark.parametrize("section", [
    box(0, 0, 60, 40),                                          # perimeters + infill
    box(0, 0, 60, 40).difference(Point(30, 20).buffer(8)),      # a hole
    box(0, 0, 80, 9.0),                                         # a two-bead wall
    box(0, 0, 60, 8).union(box(0, 0, 8, 50)),                   # an L of thin legs
], ids=["block", "holed", "wall-1.5w", "L"])
def test_every_layer_and_every_bead_class_lays_what_it_fills(section):
    job = plan_part(extrude(section, 3.0), PlanOptions(width_mm=6.0, allow_underfill=True), MAT)
    for layer in job.layers:
        laid = sum(_laid(p) for p in layer.passes)
        assert laid == pytest.approx(section.area * layer.height_mm, rel=0.03), layer.index
        per_class = _class_areas(section, layer, 0.3)
        for role, area in per_class.items():
            mine = sum(_laid(p) for p in layer.passes if p.role == role)
            assert mine == pytest.approx(area * layer.height_mm, rel=0.03, abs=0.005 * laid), role



@settings(max_examples=25, deadline=None)
@given(length=st.floats(30.0, 120.0), rows=st.integers(2, 6), spacing=st.floats(3.5, 5.5))
def test_partition_of_parallel_rows_is_their_strips(length, rows, spacing):
    """Rows `spacing` apart in a rectangle whose edges lie half a spacing beyond the outer rows:
    each row fills a strip of the spacing (the ends included), and the shares tile the area."""
    width = rows * spacing
    island = shapely.box(0.0, 0.0, length, width)
    beads = [Path2D("infill", np.array([[3.0, (k + 0.5) * spacing], [length - 3.0, (k + 0.5) * spacing]]), 6.0)
             for k in range(rows)]
    shares = partition_shares(island, beads, 6.0)
    lengths = np.array([b.length for b in beads])
    assert float(np.sum(shares * lengths)) == pytest.approx(island.area, rel=1e-9)
    # the inner rows own their strip exactly; the ends of the strip go to the row too
    for s, ln in zip(shares[1:-1], lengths[1:-1]):
        assert s * ln == pytest.approx(spacing * length, rel=0.02)

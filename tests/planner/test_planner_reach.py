"""Variable bead width before "unplannable" (issue 28 item 2): where the nominal beads leave an
island under --min-coverage, narrower legal beads (each with its own welding point) fill what they
can reach; the envelope still holds."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from core.config import load_material
from planner.plan import PlanOptions, plan_part
from planner.process import inverse
from planner.thin import legal_widths

MAT = load_material("inconel718-1.0mm")
WIRE = np.pi * MAT.wire_diameter_mm ** 2 / 4


@pytest.fixture(scope="module")
def torus_job():
    """The torus at 4 mm beads: its layer 7 was 94.0 % covered by the nominal beads (a ring about
    0.9 mm wide between the loops, 222 mm2)."""
    torus = trimesh.creation.torus(major_radius=40.0, minor_radius=10.0, major_sections=96, minor_sections=48)
    return plan_part(torus, PlanOptions(width_mm=4.0, allow_overhang=True), MAT)


def test_every_layer_reaches_the_coverage_target(torus_job):
    assert torus_job.summary["coverage_min"] >= 0.97
    assert all(L.extra["coverage"] >= 0.97 for L in torus_job.layers)


def test_the_narrower_beads_are_legal_and_balanced(torus_job):
    h = torus_job.layers[0].height_mm
    wd = legal_widths(MAT, h, 4.0, 0.738, False)
    k = MAT.ribeiro
    for layer in torus_job.layers:
        for p in layer.passes:
            assert wd.lo - 1e-3 <= p.width_mm <= wd.hi + 1e-3
            assert k.i_min_a - 1e-6 <= p.current_a <= k.i_max_a + 1e-6
            assert k.wfs_min_m_min - 1e-6 <= p.wfs_m_min <= k.wfs_max_m_min + 1e-6
            pp = inverse(MAT, p.width_mm, h)  # its own welding point
            assert p.current_a == pytest.approx(pp.current_a, rel=1e-6) or p.speed_mm_min in (6000.0, 30.0)
    assert torus_job.summary["mass_balance_layer_max"] <= 0.03
    assert torus_job.summary["mass_balance_max_error"] <= 0.001


def test_near_net_a_hole_a_bead_fits_in_is_filled_though_the_island_is_covered_enough():
    """A 100 mm square whose scan lines stop short of a 9 x 9 mm hole (99 % covered): a net plan leaves
    it to the coverage rule; near-net, where the part's own surface may lie in such a hole (a thin ring
    meeting the body, the octagonal pocket at 8 mm), a bead is laid along it."""
    import shapely

    from planner.path2d import Path2D
    from planner.reach import footprint, reach_fill

    wd = legal_widths(MAT, inverse(MAT, 6.0).height_mm, 6.0, 0.74, False)
    island = shapely.box(0, 0, 100, 100)
    hole = shapely.box(45.5, 45.5, 54.5, 54.5)
    beads = []
    for y in np.arange(3.0, 100.0, 6.0):  # rows 6 mm apart, cut where they would cross the hole
        rest = shapely.LineString([(0.0, y), (100.0, y)]).difference(hole.buffer(3.0))
        beads += [Path2D("infill", np.asarray(g.coords)[:, :2], 6.0, False, 6.0)
                  for g in getattr(rest, "geoms", [rest]) if g.length > 0]
    assert island.difference(footprint(beads)).area < 0.03 * island.area
    assert reach_fill(island, beads, wd, 0.97, 12.0, 0.0) == []
    extra = reach_fill(island, beads, wd, 0.97, 12.0, 1.5)
    assert extra and footprint(extra).intersection(hole).area >= 0.4 * hole.area  # one bead along its axis

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

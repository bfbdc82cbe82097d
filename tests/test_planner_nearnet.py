"""Near-net planning (issue 28 item 1, DESIGN.md §3.9): --machining-allowance grows every layer
and the top; coverage, outside and mass balance against the grown region; stock per face; the
refused features an allowance would make buildable."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
from shapely.geometry import box

from core.config import load_material
from core.errors import InputError, MeshError
from planner.extrude import extrude
from planner.nearnet import allowance_for, grow
from planner.plan import PlanOptions, plan_part
from planner.thin import legal_widths

MAT = load_material("inconel718-1.0mm")
WIRE = np.pi * MAT.wire_diameter_mm ** 2 / 4
RIB = extrude(box(0, 0, 80, 3.0), 10.0)  # a 3 mm rib: narrower than the smallest legal bead (4.47 mm)


def test_a_rib_too_thin_for_a_bead_is_refused_naming_the_allowance_that_builds_it():
    with pytest.raises(MeshError) as err:
        plan_part(RIB, PlanOptions(width_mm=6.0), MAT)
    msg = str(err.value)
    assert "3.00 mm wide" in msg and "buildable with --machining-allowance 0.75 mm" in msg
    assert "--machining-allowance 0.75 would make 15 of the" in msg


def test_the_allowance_builds_it_oversize_and_carries_the_stock_per_face():
    job = plan_part(RIB, PlanOptions(width_mm=6.0, machining_allowance_mm=1.5), MAT)
    h = job.layers[0].height_mm
    grown = box(0, 0, 80, 3.0).buffer(1.5, quad_segs=8)
    for layer in job.layers:
        fp = shapely.union_all([shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2)
                                for p in layer.passes])
        assert fp.intersection(grown).area / grown.area >= 0.97
        assert fp.difference(grown).area / fp.area <= 0.03
        laid = sum(WIRE * p.wfs_m_min * 1000 / p.speed_mm_min * p.length_mm for p in layer.passes)
        assert laid == pytest.approx(grown.area * h, rel=0.03)
        assert fp.contains(box(0, 0, 80, 3.0))  # the net part is inside the deposit
    m = job.summary["machining"]
    assert m["allowance_mm"] == 1.5
    assert len(job.layers) * h >= 10.0 + 1.5 and m["stock_mm"]["top"] >= 1.5
    assert m["top_layers_added"] == len(job.layers) - 15
    assert 0.0 < m["stock_mm"]["side_min"] <= 1.5 <= m["stock_mm"]["side_max"] + 1e-3
    assert m["stock_mm"]["bottom"] == 0.0


def test_the_material_default_applies_and_the_option_overrides_it():
    mat = MAT.model_copy(update={"machining_allowance_mm": 1.0})
    job = plan_part(RIB, PlanOptions(width_mm=6.0), mat)
    assert job.summary["machining"]["allowance_mm"] == 1.0
    assert plan_part(extrude(box(0, 0, 40, 20), 2.0), PlanOptions(width_mm=6.0, machining_allowance_mm=0.0),
                     mat).summary["machining"] == {"allowance_mm": 0.0}
    with pytest.raises(InputError, match="machining-allowance"):
        PlanOptions(width_mm=6.0, machining_allowance_mm=-1.0)


def test_grow_and_allowance_for():
    assert grow([box(0, 0, 10, 10)], 1.0)[0].area == pytest.approx(144 - 4 + np.pi, rel=1e-3)
    assert len(grow([box(0, 0, 10, 10), box(11, 0, 20, 10)], 1.0)) == 1  # islands 1 mm apart merge
    wd = legal_widths(MAT, 0.66, 6.0, 0.738, False)
    assert allowance_for(3.0, wd, 12.0) == pytest.approx(0.75)  # 3 + 2·0.75 = 4.5 ≥ 4.47
    assert allowance_for(5.0, wd, 12.0) == 0.0
    assert allowance_for(7.0, wd, 12.0) > 0.0  # between one widest and two narrowest beads

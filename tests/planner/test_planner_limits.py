"""Plan-time limits (issue 28 item 6, docs/contract.md §3.10): a bead the cell cannot weld is refused at
plan time naming it, or planned under --allow-outside with `inside_envelope: false`."""
from __future__ import annotations

import json

import numpy as np
import pytest
from shapely.geometry import box

from core.config import load_material
from core.errors import MeshError
from planner.extrude import extrude
from planner.job import job_to_json, loads_job
from planner.plan import PlanOptions, plan_part
from planner.weld import CellLimits

MAT = load_material("inconel718-1.0mm")
WIRE = np.pi * MAT.wire_diameter_mm ** 2 / 4
BLOCK = extrude(box(0, 0, 60, 40), 1.5)


def _laid(p) -> float:
    """mm² a pass lays per mm, over its whole length (each segment at its own speed and wire feed)."""
    return WIRE * 1000.0 * float((p.wire_feeds() / p.speeds() * p.segment_lengths()).sum()) / p.length_mm


def test_a_bead_faster_than_the_cell_is_welded_at_its_max_speed_with_less_wire():
    """Balanced at 6 mm the overlapped beads run at about 1,700 mm/min: a cell of 1,500 keeps the
    speed at its limit and lowers the wire feed so the section is still filled, inside the envelope."""
    free = plan_part(BLOCK, PlanOptions(width_mm=6.0), MAT)
    assert max(p.speed_mm_min for L in free.layers for p in L.passes) > 1500.0
    job = plan_part(BLOCK, PlanOptions(width_mm=6.0, cell_limits=CellLimits(max_speed_mm_min=1500.0)), MAT)
    k = MAT.ribeiro
    for L, F in zip(job.layers, free.layers):
        for p, f in zip(L.passes, F.passes):
            assert p.speeds().max() <= 1500.0
            assert k.i_min_a <= p.current_a <= k.i_max_a
            assert k.wfs_min_m_min <= p.wire_feeds().min() and p.wire_feeds().max() <= k.wfs_max_m_min
            assert _laid(p) == pytest.approx(_laid(f), rel=0.01)  # the same section filled (speeds rounded to 0.1)
    assert job.summary["limits"]["wfs_adjusted_passes"] > 0
    assert job.summary["mass_balance_layer_max"] <= 0.03


def test_a_bead_the_cell_cannot_weld_is_refused_at_plan_time_naming_it():
    with pytest.raises(MeshError) as err:
        plan_part(BLOCK, PlanOptions(width_mm=6.0, cell_limits=CellLimits(max_speed_mm_min=600.0)), MAT)
    msg = str(err.value)
    assert "outside the cell's limits" in msg and "layer 0: pass" in msg and "mm wide" in msg
    assert "above the cell's max speed 600 mm/min" in msg and "below Imin" in msg


def test_allow_outside_plans_it_flagged_in_the_job():
    opt = PlanOptions(width_mm=6.0, allow_outside=True, cell_limits=CellLimits(max_speed_mm_min=600.0))
    job = plan_part(BLOCK, opt, MAT)
    flagged = [p for L in job.layers for p in L.passes if not p.inside_envelope]
    assert flagged and all(p.speed_mm_min <= 600.0 for L in job.layers for p in L.passes)
    d = json.loads(job_to_json(job))
    assert any(p.get("inside_envelope") is False for L in d["layers"] for p in L["passes"])
    assert not loads_job(job_to_json(job)).layers[0].passes[0].inside_envelope
    assert job.summary["limits"]["outside_passes"] == len(flagged)
    assert any("max speed" in w for w in job.summary["warnings"])


def test_inside_the_limits_the_job_carries_no_flag():
    d = json.loads(job_to_json(plan_part(BLOCK, PlanOptions(width_mm=6.0), MAT)))
    assert all("inside_envelope" not in p for L in d["layers"] for p in L["passes"])


def test_allow_outside_never_extrapolates_to_no_wire():
    """A 1.8 mm gap bead at 2 mm layers is below the synergic line's zero: it gets the nearest
    weldable width instead of a negative wire feed and speed."""
    from planner.weld import Process

    proc = Process(MAT, 2.0, True, 6.0)
    pp = proc.point(1.8)
    assert pp.wfs_m_min > 0 and pp.current_a > 0 and pp.speed_mm_min > 0


def test_a_bead_too_small_for_the_cell_is_dropped_where_its_neighbours_cover_it_not_refused():
    """Issue 40 item 2: a wall 5.2 mm thick at 4 mm beads gets a lone bead and two short beads at its
    ends that mostly lie on it. A cell of 2,000 mm/min cannot lay so little metal a mm even at the
    least wire feed: the plan was refused naming them; now they are dropped (named in the summary)
    and the wall is planned inside the cell's limits, its coverage within 1 % of the unlimited plan."""
    wall = extrude(box(0, 0, 80, 5.2), 2.0)
    free = plan_part(wall, PlanOptions(width_mm=4.0, allow_underfill=True), MAT)
    job = plan_part(wall, PlanOptions(width_mm=4.0, allow_underfill=True,
                                      cell_limits=CellLimits(max_speed_mm_min=2000.0)), MAT)
    k = MAT.ribeiro
    for L in job.layers:
        for p in L.passes:
            assert p.speed_mm_min <= 2000.0 and p.inside_envelope
            assert k.i_min_a <= p.current_a <= k.i_max_a and k.wfs_min_m_min <= p.wfs_m_min <= k.wfs_max_m_min
    assert job.summary["limits"]["outside_passes"] == 0
    assert job.summary["coverage_min"] >= free.summary["coverage_min"] - 0.01
    assert job.summary["mass_balance_layer_max"] <= 0.03
    assert any("dropped: its" in s and "share is less metal than the cell lays" in s for s in job.summary["stubs"])


def test_a_pocket_bead_too_small_for_the_cell_is_dropped_its_section_shared_not_refused():
    """Issue 40 item 2: a plate with two holes at 6 mm beads has a pocket bead in a corner whose share
    (1.8 mm) is less metal a mm than a 2,500 mm/min cell lays at the least wire feed. It was refused
    (needs 4,250 mm/min); now it is dropped, named, and its section goes to its neighbours: every pass
    inside the cell's limits and the layer's metal still balanced."""
    from shapely.geometry import Point

    plate = extrude(box(0, 0, 60, 40).difference(Point(20, 20).buffer(6)).difference(Point(42, 20).buffer(4)), 1.5)
    job = plan_part(plate, PlanOptions(width_mm=6.0, cell_limits=CellLimits(max_speed_mm_min=2500.0)), MAT)
    assert any("gap bead at (7.7, 7.8)" in s and "its section goes to its neighbours" in s for s in job.summary["stubs"])
    assert all(p.speeds().max() <= 2500.0 and p.inside_envelope for L in job.layers for p in L.passes)
    assert job.summary["limits"]["outside_passes"] == 0
    assert job.summary["mass_balance_layer_max"] <= 0.03 and job.summary["coverage_min"] >= 0.97

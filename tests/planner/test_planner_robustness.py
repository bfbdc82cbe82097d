"""Robustness: a sphere with deleted faces, and the real parts of ../shared/parts."""
from __future__ import annotations

import numpy as np
import pytest

from core.config import load_material
from core.errors import MeshError
from planner.plan import PlanOptions, plan_part

from tests import planner_parts as parts

MAT = load_material("inconel718-1.0mm")


def test_sphere_with_a_thousandth_of_its_faces_deleted_is_still_planned():
    job = plan_part(parts.sphere_with_holes(0.001), PlanOptions(width_mm=6.0, allow_overhang=True), MAT)
    r = 40.0
    for L in job.layers:
        zc = L.z_mm - L.height_mm / 2 - r
        true_area = np.pi * (r * r - zc * zc)
        # The layer the planner filled is the sphere's section, gaps bridged: >= 99 % of it.
        assert L.extra["area_mm2"] >= 0.99 * true_area * 0.995, L.index
        assert L.extra["coverage"] >= 0.95, L.index
    assert job.summary["closed_gaps"] > 0 or any("filled" in r for r in job.summary["repairs"])


@pytest.mark.parametrize("name, units, outcome", [
    ("plate_holes.STL", "mm", "layer 1: steps out 1.4"),  # a chamfered bottom edge: 45 deg, over the rule
    ("featuretype.STL", "mm", "smaller than one bead"),
    ("featuretype.STL", "inch", "3.00 mm wide, narrower than the smallest legal bead"),
    ("teapot.stl", "mm", "open contour"),
    ("empty.stl", "mm", "no triangles"),
])
def test_real_parts_plan_or_fail_clearly(shared_parts, name, units, outcome):
    path = shared_parts / name
    if not path.exists():
        pytest.skip(f"{name} not in ../shared/parts")
    opts = PlanOptions(width_mm=6.0, units=units)
    with pytest.raises(MeshError, match=outcome):
        plan_part(path, opts, MAT)


@pytest.mark.parametrize("name, units, cov_min", [("plate_holes.STL", "mm", 0.97), ("featuretype.STL", "inch", 0.85)])
def test_real_parts_plan_when_what_they_break_is_allowed(shared_parts, name, units, cov_min):
    path = shared_parts / name
    if not path.exists():
        pytest.skip(f"{name} not in ../shared/parts")
    opts = PlanOptions(width_mm=6.0, units=units, allow_overhang=True, allow_underfill=True)
    job = plan_part(path, opts, MAT)
    s = job.summary
    assert s["coverage_min"] >= cov_min and s["overfill"] <= 0.03 and s["mass_balance_max_error"] <= 0.03
    assert s["overhang_layers"] and s["warnings"]  # what was allowed is listed, not hidden
    assert job.source.file == name

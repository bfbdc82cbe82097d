"""Robustness: a sphere with deleted faces, and the real parts of ../shared/parts."""
from __future__ import annotations

import numpy as np
import pytest

from controller.config import load_material
from planner.errors import MeshError
from planner.plan import PlanOptions, plan_part

import planner_parts as parts

MAT = load_material("inconel718-1.0mm")


def test_sphere_with_a_thousandth_of_its_faces_deleted_is_still_planned():
    job = plan_part(parts.sphere_with_holes(0.001), PlanOptions(width_mm=6.0), MAT)
    r = 40.0
    for L in job.layers:
        zc = L.z_mm - L.height_mm / 2 - r
        true_area = np.pi * (r * r - zc * zc)
        # The layer the planner filled is the sphere's section, gaps bridged: >= 99 % of it.
        assert L.extra["area_mm2"] >= 0.99 * true_area * 0.995, L.index
        assert L.extra["coverage"] >= 0.95, L.index
    assert job.summary["closed_gaps"] > 0 or any("filled" in r for r in job.summary["repairs"])


@pytest.mark.parametrize("name, units, outcome", [
    ("plate_holes.STL", "mm", "plan"),
    ("featuretype.STL", "mm", "smaller than one bead"),
    ("featuretype.STL", "inch", "plan"),
    ("teapot.stl", "mm", "open contour"),
    ("empty.stl", "mm", "no triangles"),
])
def test_real_parts_plan_or_fail_clearly(shared_parts, name, units, outcome):
    path = shared_parts / name
    if not path.exists():
        pytest.skip(f"{name} not in ../shared/parts")
    opts = PlanOptions(width_mm=6.0, units=units)
    if outcome == "plan":
        job = plan_part(path, opts, MAT)
        assert job.summary["coverage"] >= 0.9 and job.summary["overfill"] <= 0.01
        assert job.source.file == name
    else:
        with pytest.raises(MeshError, match=outcome):
            plan_part(path, opts, MAT)

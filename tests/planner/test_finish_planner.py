"""The finishing planner's pure parts: scallop, drop-cutter (against opencamlib and brute force),
roughing depth per pass, finishing to CAD, the gouge check (planner/dropcutter.py, planner/finish.py)."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from planner.dropcutter import ToolShape, drop_map, drop_mesh, scallop_height, stepover_for_scallop
from planner.finish import Cut, Pass, Surface, gouge_depth, plan_finish, stock_margin


def _tilted_block() -> np.ndarray:
    box = trimesh.creation.box(extents=(20, 20, 10))
    box.apply_translation((0, 0, -5))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.3, (1, 0.5, 0)))
    return np.asarray(box.triangles)


def test_scallop_of_a_6mm_ball_and_the_stepover_that_keeps_it_under_10_microns():
    ball = ToolShape("ball", 3.0)
    assert scallop_height(ball, 0.5) == pytest.approx(0.0104, abs=1e-4)   # the figure
    s = stepover_for_scallop(ball, 0.01, 2.0)
    assert scallop_height(ball, s) == pytest.approx(0.01, abs=1e-9) and 0.48 < s < 0.5
    assert stepover_for_scallop(ToolShape("flat", 4.0), 0.01, 4.0) == 4.0   # flat: no scallop on a flat face


_OCL = """
import json, sys
from opencamlib import ocl
tri, xy, kind = json.load(sys.stdin)
surf = ocl.STLSurf()
for t in tri:
    surf.addTriangle(ocl.Triangle(*[ocl.Point(*p) for p in t]))
bdc = ocl.BatchDropCutter()
bdc.setSTL(surf)
bdc.setCutter(ocl.BallCutter(6.0, 20.0) if kind == "ball" else ocl.CylCutter(6.0, 20.0))
for x, y in xy:
    bdc.appendPoint(ocl.CLPoint(x, y, -100.0))
bdc.run()
print(json.dumps([p.z for p in bdc.getCLPoints()]))
"""


@pytest.mark.parametrize("kind", ["ball", "flat"])
def test_drop_cutter_on_a_mesh_agrees_with_opencamlib(kind):
    pytest.importorskip("opencamlib", reason="opencamlib has wheels only up to Python 3.11")
    tri = _tilted_block()
    xy = np.random.default_rng(1).uniform(-14, 14, (300, 2))
    # its own process: its OpenMP batch crashes inside the test process (beside scipy's threads)
    out = subprocess.run([sys.executable, "-c", _OCL], input=json.dumps([tri.tolist(), xy.tolist(), kind]),
                         capture_output=True, text=True, timeout=60, check=True)
    theirs = np.array(json.loads(out.stdout))
    ours = drop_mesh(ToolShape(kind, 3.0), tri, xy)
    on = np.isfinite(ours)
    assert on.sum() > 200 and np.all(theirs[~on] == -100.0)        # off the part: both say so
    assert np.abs(ours[on] - theirs[on]).max() < 1e-9


def test_drop_cutter_on_a_height_map_is_the_brute_force_minimum_clearance():
    rng = np.random.default_rng(3)
    h = rng.uniform(0, 2, (30, 30))
    tool = ToolShape("ball", 1.6)
    got = drop_map(tool, h, (0.0, 0.0), 0.5)
    j, i = 12, 17   # brute force: the tool's tip where no grid point of the map is above its surface
    best = -math.inf
    for jj in range(30):
        for ii in range(30):
            r = math.hypot(ii - i, jj - j) * 0.5
            if r <= 1.6:
                best = max(best, h[jj, ii] - (1.6 - math.sqrt(1.6 ** 2 - r * r)))
    assert got[j, i] == pytest.approx(best, abs=1e-12)


def _cad_and_stock() -> tuple[np.ndarray, Surface]:
    cad = trimesh.creation.box(extents=(60, 60, 20))
    cad.apply_translation((0, 0, -10))
    xs = np.arange(-15, 15.01, 0.5)
    gx, gy = np.meshgrid(xs, xs)
    h = 1.8 + 0.4 * np.sin(gx / 2) * np.cos(gy / 3)   # a rippled deposit 1.4…2.2 mm over the top
    return np.asarray(cad.triangles), Surface(h, (-15.0, -15.0), 0.5)


def test_roughing_takes_at_most_the_depth_of_cut_and_finishing_lands_on_cad():
    tri, stock = _cad_and_stock()
    cut = Cut("ball6", ToolShape("ball", 3.0), max_depth_of_cut_mm=0.8, max_stepover_mm=2.0, feed_mm_min=900)
    plan = plan_finish(tri, stock, (-12, -12, 12, 12), cut, finish_stock_mm=0.2, scallop_mm=0.01)
    rough = [p for p in plan.passes if p.kind == "rough"]
    fin = [p for p in plan.passes if p.kind == "finish"]
    levels = sorted({round(float(p.points[:, 2].min()), 6) for p in rough}, reverse=True)
    steps = -np.diff([2.2] + levels)
    assert len(levels) == plan.levels >= 3 and steps.max() <= 0.8 + 1e-9
    assert levels[-1] == pytest.approx(0.2, abs=1e-9)            # roughing stops at CAD + finishing stock
    assert len(fin) == 1 and np.abs(fin[0].points[:, 2]).max() < 1e-9   # finishing: the CAD top
    assert plan.scallop_mm <= 0.01 and plan.gouge_mm <= 1e-9
    assert plan.removal_mm3 == pytest.approx(1.8 * 30.5 * 30.5, rel=0.02)


def test_gouge_check_finds_a_tool_below_cad_with_the_tool_shape():
    tri = _tilted_block()
    ball = ToolShape("ball", 3.0)
    xy = np.array([[0.0, 0.0], [4.0, 0.0]])
    z = drop_mesh(ball, tri, xy)
    ok = Pass("finish", np.column_stack([xy, z]))
    assert gouge_depth(tri, ball, [ok]) == pytest.approx(0.0, abs=1e-12)
    low = Pass("finish", np.column_stack([xy, z - [0.0, 0.03]]))
    assert gouge_depth(tri, ball, [low]) == pytest.approx(0.03, abs=1e-9)


def test_stock_margin_is_the_height_over_the_cad_top():
    tri, _ = _cad_and_stock()
    m = stock_margin(tri, np.array([[0.0, 0.0, 0.35], [5.0, 5.0, -0.1], [100.0, 0.0, 1.0]]))
    assert m[0] == pytest.approx(0.35) and m[1] == pytest.approx(-0.1) and math.isnan(m[2])

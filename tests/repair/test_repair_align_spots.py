"""The repair's alignment touches chosen off the repair region (issue 36 item 7): a pocket anywhere
on the top face is aligned from the intact face around it; refused only when too little is left."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.align.intact import intact_spots, keep_out_mm
from controller.cli.main import main
from controller.harness.align_sim import run_with_sim
from controller.harness.repair_parts import posed_sim
from controller.job.read import read_job
from controller.job.repair_volume import to_manifold, to_trimesh
from controller.motion.kinematics import Trunnion
from controller.repair import probe_plan
from core.config import load_cell
from core.errors import InputError
from sims.workpiece import rot, trans

pytestmark = pytest.mark.realtime  # the last test runs a cell on the wall clock (tests/conftest.py)


def _parts(tmp: Path) -> tuple[Path, Path]:
    """A 50 × 34 × 15 block and its stock with a 14 × 10 mm pocket, 2 deep, at x 6…20, y −14…−4."""
    cad = trimesh.creation.box(extents=(50, 34, 15))
    cad.apply_translation((0, 0, -7.5))
    pocket = trimesh.creation.box(extents=(14, 10, 2))
    pocket.apply_translation((13, -9, -1))
    cad.export(tmp / "cad.stl")
    to_trimesh(to_manifold(cad, "cad") - to_manifold(pocket, "pocket")).export(tmp / "stock.stl")
    return tmp / "cad.stl", tmp / "stock.stl"


def _box_distance(xy: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    d = np.maximum(np.maximum(lo[:2] - xy, xy - hi[:2]), 0.0)
    return np.hypot(d[:, 0], d[:, 1])


def test_the_spots_lie_on_the_intact_top_off_the_region_and_spread_wide(tmp_path: Path):
    cad, stock = _parts(tmp_path)
    job = tmp_path / "job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.5",
                 "--out", str(job), "--allow-underfill"]) == 0
    j = read_job(job)
    rb = np.asarray(j.repair.bounds_mm)
    plan = probe_plan(trimesh.load_mesh(str(cad)), j)   # refused before this issue: "covers the middle"
    assert len(plan.top_xy) == 9
    reach = keep_out_mm(plan.top_xy)                                    # the unmeasured pose's reach there
    assert np.all(_box_distance(plan.top_xy, rb[0], rb[1]) >= reach)    # none on the region or near it
    assert np.all(np.abs(plan.top_xy) <= np.array([25.0, 17.0]) - reach[:, None])   # none near the edges
    assert np.ptp(plan.top_xy[:, 0]) >= 30 and np.ptp(plan.top_xy[:, 1]) >= 15   # a wide base for the plane
    # the 2 mm pocket stays 3 mm above the side touches (5 mm deep): the +X row and the −Y touch
    # are the routine's own; a deeper region reaching those faces moves them (the next test)
    assert plan.side_y.tolist() == [-7.0, -3.5, 0.0, 3.5, 7.0] and plan.tertiary_xy == (0.0, -17.0)


def test_too_little_intact_face_is_refused_saying_how_much():
    cad = trimesh.creation.box(extents=(50, 34, 15))
    cad.apply_translation((0, 0, -7.5))
    with pytest.raises(InputError) as e:   # a region over the −Y half: a strip 6 mm wide is left
        intact_spots(np.asarray(cad.triangles), np.array([[-30.0, -20.0, -1.0], [30.0, -3.0, 0.5]]))
    msg = str(e.value)
    assert "too little intact top face" in msg and "207 mm² spanning 34.0 × 6.0 mm" in msg, msg
    assert "needs at least 8 mm across" in msg
    with pytest.raises(InputError, match="intact −Y face .* 0.0 mm free"):   # deep: the −Y face is worn too
        intact_spots(np.asarray(cad.triangles), np.array([[-30.0, -20.0, -7.0], [30.0, -7.0, 0.5]]), face_z=-5.0)
    spots = intact_spots(np.asarray(cad.triangles), np.array([[-30.0, -20.0, -2.0], [30.0, -7.0, 0.5]]), face_z=-5.0)
    assert spots.tertiary_x == pytest.approx(0.0)   # shallow: the −Y face below it stays intact


async def test_a_pocket_off_the_middle_is_aligned_from_the_face_around_it(tmp_path: Path):
    cad, stock = _parts(tmp_path)
    job = tmp_path / "job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.5",
                 "--out", str(job), "--allow-underfill"]) == 0
    plan = probe_plan(trimesh.load_mesh(str(cad)), read_job(job))
    sim = posed_sim(stock, 1.5, -1.2, 2.0, (4.0, -3.0, 0.5))
    sim = sim.model_copy(update={"cnc": sim.cnc.model_copy(update={"probe_noise_mm": 0.002})})
    cell = load_cell()
    cell = cell.model_copy(update={"cell": cell.cell.model_copy(update={"time_scale": 1000.0})})
    res = await run_with_sim(cell, sim, plan)
    wp = sim.cnc.workpiece
    pose = rot((0, 1, 0), wp.tilt_b_deg) @ rot((1, 0, 0), wp.tilt_a_deg) @ rot((0, 0, 1), wp.rotation_c_deg)
    truth = Trunnion().matrix(res.level_a_deg, res.level_b_deg) @ trans(wp.offset_mm) @ pose
    corners = np.array([[x, y, z, 1.0] for x in (-25, 25) for y in (-17, 17) for z in (-15, 0)])
    err = np.linalg.norm((corners @ res.transform.T - corners @ truth.T)[:, :3], axis=1)
    assert err.max() < 0.03, err                                        # the CAD where the part is
    assert res.top.outliers == () and res.residual_tilt_deg < 0.01      # no touch fell into the pocket

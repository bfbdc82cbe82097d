"""Hybrid repair (issue 17): frames, one alignment, the repair volume, the alignment driving the machine."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.motion.kinematics import apply_to_job
from controller.cli.main import main
from controller.motion.cnc5 import Five
from controller.job.model import CellJob
from controller.job.repair_volume import to_manifold, to_trimesh
from core.errors import InputError
from tests.jobs import JobSpec, PassSpec, small_job


def block_with_pocket(tmp: Path) -> tuple[Path, Path]:
    """A 60×40×20 block (top at z = 0) and the same block with a 20×15×6 pocket milled into a corner."""
    cad = trimesh.creation.box(extents=(60, 40, 20))
    cad.apply_translation((0, 0, -10))
    pocket = trimesh.creation.box(extents=(20, 15, 6))
    pocket.apply_translation((20, 12.5, -3))
    stock = to_trimesh(to_manifold(cad, "cad") - to_manifold(pocket, "pocket"))
    cad.export(tmp / "cad.stl")
    stock.export(tmp / "stock.stl")
    return tmp / "cad.stl", tmp / "stock.stl"


def test_repair_plan_fills_only_the_pocket_in_the_cad_frame(tmp_path, capsys):
    cad, stock = block_with_pocket(tmp_path)
    out = tmp_path / "r.json"
    rc = main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.5",
               "--overhang", "0", "--out", str(out), "--json"])
    summary = json.loads(capsys.readouterr().out)
    assert rc == 0 and summary["frame"] == "cad"
    assert abs(summary["repair_volume_mm3"] - 20 * 15 * 6.5) < 1.0  # the pocket plus the allowance above it
    job = json.loads(out.read_text())
    pts = np.vstack([p["points"] for L in job["layers"] for p in L["passes"]])
    assert job["frame"] == "cad" and job["repair"]["allowance_mm"] == 0.5
    assert pts[:, 0].min() >= 10 and pts[:, 0].max() <= 30 and pts[:, 1].min() >= 5 and pts[:, 1].max() <= 20
    assert -6.0 < pts[:, 2].min() < -5.0 and 0.0 < pts[:, 2].max() <= 0.5 + 0.7  # from the pocket floor up


def test_a_repair_reaching_free_edges_is_planned_half_a_bead_beyond_them(tmp_path, capsys):
    """The corner pocket reaches the block's +X and +Y side faces: the repair hangs 2 mm (half the
    4 mm bead) beyond both and their corner, with the pocket's cross-section; never over the intact
    top, never beyond the pocket's own ends along the edge (docs/repair.md "Free edges")."""
    cad, stock = block_with_pocket(tmp_path)
    out = tmp_path / "r.json"
    rc = main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.5",
               "--out", str(out), "--json"])
    summary = json.loads(capsys.readouterr().out)
    hang = 2 * (15 * 6.5) + 2 * (20 * 6.5) + 2 * 2 * 6.5       # beyond +X, beyond +Y, their corner
    assert rc == 0 and abs(summary["overhang_mm3"] - hang) < 1.0
    assert abs(summary["repair_volume_mm3"] - (20 * 15 * 6.5 + hang)) < 1.0
    assert summary["bounds_mm"][0][:2] == [10.0, 5.0] and summary["bounds_mm"][1][:2] == [32.0, 22.0]
    job = json.loads(out.read_text())
    assert job["repair"]["overhang_mm"] == 2.0
    pts = np.vstack([p["points"] for L in job["layers"] for p in L["passes"]])
    assert pts[:, 0].max() > 29.5 and pts[:, 1].max() > 19.5      # the outer beads ride on the edges
    assert pts[:, 0].min() >= 10 and pts[:, 1].min() >= 5


def test_repair_plan_says_when_there_is_nothing_to_repair_or_the_stock_sticks_out(tmp_path, capsys):
    cad, stock = block_with_pocket(tmp_path)
    assert main(["repair", "plan", str(cad), "--stock", str(cad), "--width", "4"]) == 2
    assert "nothing to repair" in capsys.readouterr().err
    assert main(["repair", "plan", str(stock), "--stock", str(cad), "--width", "4"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "sticks out of the CAD by 1800.0 mm³" in err


def test_plan_frame_cad_keeps_the_cad_coordinates(tmp_path, capsys):
    patch = trimesh.creation.box(extents=(20, 20, 4))
    patch.apply_translation((0, 0, -10))  # a patch modelled from z = -12 to -8
    stl = tmp_path / "patch.stl"
    patch.export(stl)
    for frame, lo in (("cad", -12.0), ("substrate", 0.0)):
        out = tmp_path / f"{frame}.json"
        assert main(["plan", str(stl), "--width", "4", "--frame", frame, "--out", str(out)]) == 0
        job = json.loads(out.read_text())
        z = np.vstack([p["points"] for L in job["layers"] for p in L["passes"]])[:, 2]
        assert job["frame"] == frame and lo < z.min() < lo + 1.0 and z.max() <= lo + 4.0 + 1e-6


def _job(frame: str = "cad") -> CellJob:
    return small_job([[PassSpec([[0, 0, 1], [10, 0, 1]], width=4.0, normals=[[0, -1, 0], [0, -1, 0]])]],
                     JobSpec(width=4.0, step_over=3.0, frame=frame))


def test_a_job_holds_at_most_one_alignment():
    tf = np.eye(4)
    tf[:3, 3] = (1, 2, 3)
    once = apply_to_job(_job(), tf, {"level_a_deg": 0.5, "level_b_deg": -0.3, "probed_at": time.time()})
    assert once.layers[0].passes[0].points[0].tolist() == [1, 2, 4]
    with pytest.raises(InputError, match="second one is refused"):
        apply_to_job(once, tf)


def test_the_cnc_refuses_an_unaligned_cad_job_and_a_stale_alignment():
    from controller.motion.kinematics import Trunnion

    five = Five(Trunnion())
    with pytest.raises(InputError, match="CAD frame and carries no alignment"):
        five.check_alignment(_job("cad"), reset_at=0.0)
    aligned = apply_to_job(_job(), np.eye(4), {"table_deg": {"a": 0.8, "b": -0.5}, "probed_at": 100.0})
    with pytest.raises(InputError, match="before the CNC's last homing, reset or power-up"):
        five.check_alignment(aligned, reset_at=200.0)
    five.check_alignment(aligned, reset_at=50.0)
    assert five.level_lines()[-1] == "G0 A0.8000 B-0.5000"
    five.check_alignment(_job("substrate"), reset_at=0.0)  # a substrate job needs none
    assert five.level_lines() == []

"""`cell repair run --sim` end to end (issue 17): the deposit lands on the posed stock, and is verified."""
from __future__ import annotations

import json
from pathlib import Path

from bench.repair import make_parts, one, posed_sim
from controller.cli.main import main


async def test_repair_lands_in_the_pocket_of_a_posed_stock_and_verifies_its_height(tmp_path: Path):
    fig = await one(tmp_path, (1.7, -1.2, -4.5, (4.0, -3.0, 2.0)))
    assert abs(fig["alignment"]["face_angle_deg"] + 4.5) < 0.05
    assert fig["max_lateral_mm"] < 0.05 and fig["max_dz_mm"] < 0.05, fig   # in the workpiece frame
    assert abs(fig["deposited_mm"] - fig["planned_mm"]) < 0.1, fig
    v = fig["verify"]
    # On the physical deposit of DESIGN.md §6b (a height map: ripple between beads, rounded edges at the
    # pocket walls) the open-loop top is within 0.5 mm of the plan, not the 0.1 mm the box-shaped deposit
    # gave; the verify names every touch beyond its 0.1 mm tolerance as a defect (the known gap of issue 29).
    assert v["points"] == 16 and v["height_error_max_mm"] < 0.8, v
    assert abs(v["height_error_mean_mm"]) < 0.5, v


def test_repair_run_cli_reports_and_refuses_an_aligned_job(tmp_path: Path, capsys):
    cad, stock = make_parts(tmp_path)
    job = tmp_path / "job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--out", str(job)]) == 0
    d = json.loads(job.read_text())
    d["alignment"] = {"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
    (tmp_path / "aligned.json").write_text(json.dumps(d))
    assert main(["repair", "run", str(tmp_path / "aligned.json"), "--sim"]) == 2
    assert "already carries an alignment" in capsys.readouterr().err


async def test_the_repair_job_built_without_its_alignment_is_refused_before_motion(tmp_path: Path):
    from controller.api import CellController
    from controller.harness.sim import SimHarness, with_urls
    from core.config import load_cell

    cad, stock = make_parts(tmp_path)
    job = tmp_path / "job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--out", str(job)]) == 0
    cfg = with_urls(load_cell(), {}, time_scale=60)
    cfg = cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"platform": "cnc"})})
    harness = SimHarness(cfg, posed_sim(stock, 1.0, 0.5, 2.0, (1.0, 1.0, 0.0)), log_dir=tmp_path / "log")
    cfg = with_urls(cfg, harness.start())
    ctl = CellController(cfg, runs_dir=tmp_path / "runs")
    try:
        await ctl.connect(reply_timeout_ms=500.0)
        ctl.open_job(job)
        res = await ctl.start()
        events = ctl.journal.query("SELECT message FROM events WHERE kind = 'alarm'")
    finally:
        await ctl.close()
        harness.stop()
    assert res.state == "fault" and res.passes_done == 0
    assert any("CAD frame and carries no alignment" in e[0] for e in events), events
    deposit = tmp_path / "log" / "deposit.jsonl"
    assert not deposit.exists() or deposit.read_text() == ""  # not built in the wrong place
    moves = [json.loads(s)["line"] for s in (tmp_path / "log" / "cnc.jsonl").read_text().splitlines()]
    assert not any(m.startswith(("G0", "G1")) for m in moves)  # refused before any motion


def test_verify_touches_land_on_the_planned_deposit_of_an_l_shaped_worn_region(tmp_path: Path, capsys):
    """Issue 29: the verify touches come from the planned bead footprints, not the bounding box."""
    from bench.repair import touches_on_deposit, worn_parts
    from controller.job.read import read_job
    from controller.repair import verify_targets

    for shape in ("L", "slot", "edge"):
        cad, stock = worn_parts(tmp_path, shape)
        job = tmp_path / f"{shape}.json"
        assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.3",
                     "--out", str(job), "--json", "--allow-underfill", "--allow-overhang"]) == 0  # the ramp rests on the stock
        out = json.loads(capsys.readouterr().out)
        assert {"volume_mm3", "layers", "passes", "arc_starts", "coverage", "frame"} <= set(out)
        d = json.loads(job.read_text())
        assert Path(d["repair"]["cad"]).is_absolute()
        xy, z, kinds = verify_targets(read_job(job), 10, 6)
        rep = {"verify": {"at": [[x, y, 0.0] for x, y in xy]}}
        assert touches_on_deposit(d, rep) == 1.0, shape
        assert "edge" in kinds and len(xy) >= 8


async def test_l_shaped_worn_edge_repair_verifies_on_deposit(tmp_path: Path):
    from bench.repair import one

    fig = await one(tmp_path, (1.38, -1.356, 0.577, (-1.319, -2.851, -1.142)), shape="L")
    v = fig["verify"]
    assert fig["state"] == "complete" and fig["on_deposit"] == 1.0, fig
    assert v["height_error_max_mm"] < 0.8 and abs(v["height_error_mean_mm"]) < 0.5, v   # see the pocket test

"""Deposit, machine, verify (issue 36): one small repair end to end on the simulators: the stock
probe, roughing and finishing to CAD on the CNC simulator that cuts, the verify against CAD."""
from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.cli.main import main
from controller.harness.repair import repair_run_sim
from controller.harness.repair_parts import posed_sim
from controller.job.read import read_job
from controller.job.repair_volume import to_manifold, to_trimesh
from controller.runtime.devices import with_urls
from core.config import load_cell

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


def _parts(tmp: Path) -> tuple[Path, Path]:
    """A 50 × 40 × 15 block and its stock with an 8 × 14 mm slot, 1.5 deep, off the middle."""
    cad = trimesh.creation.box(extents=(50, 40, 15))
    cad.apply_translation((0, 0, -7.5))
    slot = trimesh.creation.box(extents=(8, 14, 1.5))
    slot.apply_translation((-15, 8, -0.75))
    cad.export(tmp / "cad.stl")
    to_trimesh(to_manifold(cad, "cad") - to_manifold(slot, "slot")).export(tmp / "stock.stl")
    return tmp / "cad.stl", tmp / "stock.stl"


async def test_a_slot_is_deposited_machined_to_cad_and_verified(tmp_path: Path):
    cad, stock = _parts(tmp_path)
    job = tmp_path / "job.json"
    assert main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.5",
                 "--out", str(job), "--allow-underfill"]) == 0
    cell = with_urls(load_cell(), {}, time_scale=120)
    shop = tmp_path / "shop.db"   # the shop's record store gets the machining too (docs/records.md)
    cell = cell.model_copy(update={"records": cell.records.model_copy(update={"url": f"sqlite:///{shop}"})})
    maps: list = []
    sim = posed_sim(stock, 0.8, -0.6, 2.0, (1.5, -1.0, 0.3))
    # a small part cools fast (no interpass waits to sit through in a test)
    sim = sim.model_copy(update={"thermal": sim.thermal.model_copy(update={"cooling_time_constant_s": 10.0})})
    rep = await repair_run_sim(read_job(job), cell, sim,
                               job_path=job, runs_dir=tmp_path / "runs", log_dir=tmp_path / "log",
                               inspect=lambda h, r: maps.append(h.world.physics.maps["cnc"]))
    assert rep["state"] == "complete"
    st, mc, v = rep["stock"], rep["machining"], rep["verify"]
    assert st["min_mm"] >= load_cell().machining.min_stock_mm and st["points"] >= 8      # enough stock everywhere
    assert mc["tool"] == "ball6" and mc["removal_mm3"] > 0 and mc["time_s"] > 0
    # the verify against CAD, no allowance: every touch within ±0.05 mm, nothing below CAD beyond it
    assert v["against"] == "CAD" and v["height_error_max_mm"] <= 0.05 and v["below_cad_max_mm"] <= 0.05, v
    assert not v["defects"]
    # the simulator's own record: every cutting move with what it removed; the height map as machined
    cuts = [json.loads(s) for s in (tmp_path / "log" / "cut.jsonl").read_text().splitlines()]
    assert cuts and all(c["tool"] == 1 and c["removed_mm3"] > 0 for c in cuts)
    assert max(c["depth_mm"] for c in cuts) <= 1.0 + 0.3                       # a pass's depth of cut (+ scallop)
    hm = maps[0]
    xs, ys = np.meshgrid(np.arange(-18.5, -11.5, 0.5), np.arange(2.5, 13.5, 0.5))
    top = hm.solid_tops(xs.ravel(), ys.ravel())
    assert np.nanmin(top) >= -0.02 and np.nanmax(top) <= 0.05, (np.nanmin(top), np.nanmax(top))
    rec = json.loads((Path(rep["run_dir"]) / "repair.json").read_text())
    assert rec["verify"]["below_cad_max_mm"] == v["below_cad_max_mm"]
    with sqlite3.connect(shop) as db:
        rows = db.execute("SELECT tool, removal_mm3, below_cad_max_mm FROM repairs").fetchall()
    assert rows == [("ball6", mc["removal_mm3"], v["below_cad_max_mm"])], rows

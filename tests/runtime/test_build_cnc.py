"""A build on the CNC platform (grbl, G4 P0 sync points, M3/M5) against the simulators."""
from __future__ import annotations

from pathlib import Path

import pytest

from bench._coverage import coverage, read_segments
from controller.harness.cell import open_cell, with_urls
from controller.job.read import job_from_dict
from core.config import load_cell, load_sim
from tests.cells import cnc_cell, on_the_cnc_block, planned, small_job
from controller.defaults import SIM_REPLY_TIMEOUT_MS

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


async def test_cnc_build_deposits_every_planned_segment_once(tmp_path: Path) -> None:
    cfg = cnc_cell(20)
    job = on_the_cnc_block(small_job(n_layers=2))
    async with open_cell(cfg, sim=load_sim(), log_dir=tmp_path / "log", runs_dir=tmp_path / "runs",
                         reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        ctl.open_job(job_from_dict(job))
        res = await ctl.start()
        progress = ctl.journal.query("SELECT count(*) FROM progress")[0][0]
    assert res.state == "complete", res
    assert res.passes_done == 4 and res.arc_starts == 4
    segs = [s for s in read_segments(tmp_path / "log" / "deposit.jsonl") if s["device"] == "cnc"]
    cov = coverage(planned(job), segs)
    assert cov.missing_mm < 0.05 and cov.excess_mm < 0.05, cov.as_dict()
    assert progress >= 4  # points reached were journaled from the status reports


async def test_run_alignment_through_the_api_finds_the_substrate_pose(tmp_path: Path) -> None:
    cfg = with_urls(load_cell(), {}, time_scale=200)
    async with open_cell(cfg, sim=load_sim(), runs_dir=tmp_path / "runs", reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        assert "run_alignment" in ctl.allowed_commands() and "start" not in ctl.allowed_commands()
        res = await ctl.run_alignment()
        state = ctl.machine.state.value
        allowed = ctl.allowed_commands()
    assert state == "aligned" and "open_job" in allowed
    # config/sim.yaml: the block is turned 1.5° about z and tilted 0.8° / -0.5°
    assert abs(abs(res.face_angle_deg) - 1.5) < 0.05
    assert abs(abs(res.level_a_deg) - 0.8) < 0.05 and abs(abs(res.level_b_deg) - 0.5) < 0.05

"""Builds against the simulators over the real protocols: deposit ground truth, interlocks, resume."""
from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from bench._coverage import coverage, exec_log_duplicates, read_segments
from controller.job.read import job_from_dict
from controller.runtime.machine import State
from tests.cells import small_job, shorten, planned, Cell

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)



@pytest.mark.usefixtures("record_plots")  # checks the PNGs (tests/conftest.py)
async def test_a_build_deposits_every_planned_segment_exactly_once(tmp_path: Path) -> None:
    job = small_job()
    async with Cell(tmp_path, scale=20) as c:
        run_dir = c.ctl.open_job(job_from_dict(job))
        res = await c.ctl.start()
        report = c.ctl.write_report()
        # the journal's write-ahead tickets are the ones the robot executed, point for point
        mismatched = c.ctl.journal.query(
            "SELECT count(*) FROM progress p JOIN moves m ON m.ticket = p.ticket AND m.run = p.run"
            " WHERE m.layer != p.layer OR m.pass != p.pass OR m.idx != p.idx")
        counts = c.ctl.journal.query("SELECT (SELECT count(*) FROM progress), (SELECT count(*) FROM moves)")
    assert mismatched == [(0,)] and counts[0][0] == counts[0][1] > 100
    assert res.state == "complete" and res.layers_done == 3 and res.passes_done == 6 and res.arc_starts == 6
    cov = coverage(planned(job), read_segments(c.log / "deposit.jsonl"))
    assert cov.missing_mm < 0.05 and cov.excess_mm < 0.05, cov.as_dict()
    assert exec_log_duplicates(c.log / "robot.jsonl") == 0
    rep = json.loads(report.read_text())
    assert rep["state"] == "complete" and rep["layers_done"] == 3 and rep["passes_done"] == 6
    assert len(rep["per_layer"]) == 3 and all(d["heat_input_j_mm"] > 0 for d in rep["per_layer"])
    # heat input = η·U·I/v within the process window of the material (Inconel, 95..160 A)
    assert 100 < rep["per_layer"][0]["heat_input_j_mm"] < 5000
    for png in ("layers.png", "process.png", "temperature.png", "defects.png"):
        assert (run_dir / png).stat().st_size > 1000
    assert run_dir.name.startswith("square-") and (run_dir / "journal.sqlite").exists()


async def test_door_open_during_a_bead_holds_drops_start_and_resumes_without_gaps(tmp_path: Path) -> None:
    job = small_job(n_layers=2)
    async with Cell(tmp_path, scale=5) as c:
        c.ctl.open_job(job_from_dict(job))
        weld_start: list[tuple[float, int, bool]] = []
        c.ctl.devices.power.subscribe(lambda st: weld_start.append((st.t, st.cycle, st.command.weld_start)))
        build = asyncio.ensure_future(c.ctl.start())
        await c.wait_for(lambda s: s.layer == 1 and s.pass_ == 0 and s.state == "running_depositing")
        await asyncio.sleep(0.3)
        door = c.harness.sim("cellio")
        c.harness.call(door.open_door)
        res = await asyncio.wait_for(build, 10)
        assert res.state == "fault"
        trip = c.ctl.interlocks.trips[0]
        assert trip.message == "door opened during the build" and (trip.layer, trip.pass_) == (1, 0)
        # acted in the same cycle that read the input; the next power cycle carries weld start 0
        assert trip.t_acted - trip.t_detect < 0.010
        await asyncio.sleep(0.1)
        # the reply of a cycle already on the wire at the trip may still echo the old command;
        # the first cycle written after it carries weld start 0
        after = [w for w in weld_start if w[0] > trip.t_acted]
        first_off = next((w for w in after[:2] if w[2] is False), None)
        assert first_off is not None and first_off[0] - trip.t_detect < 0.05, after[:3]
        assert all(w[2] is False for w in after[after.index(first_off):])
        await asyncio.sleep(0.2)
        assert c.ctl.devices.robot.last_status.state == "HOLD"
        alarms = c.ctl.journal.query("SELECT message, layer, pass, x, y, z FROM events WHERE kind='alarm'")
        assert alarms[0][:3] == ("door opened during the build", 1, 0) and alarms[0][3] is not None
        # the latch holds until an explicit reset; then the build continues where the bead stopped
        with pytest.raises(Exception, match="not allowed"):
            await c.ctl.start()
        c.harness.call(door.close_door)
        await asyncio.sleep(0.1)
        await c.ctl.reset()
        res = await c.ctl.start()
        report = json.loads(c.ctl.write_report(plots=False).read_text())
    assert res.state == "complete" and res.passes_done == 4
    cov = coverage(planned(job), read_segments(c.log / "deposit.jsonl"))
    assert cov.missing_mm < 0.05 and cov.excess_mm < 2.0, cov.as_dict()
    assert exec_log_duplicates(c.log / "robot.jsonl") == 0
    assert report["defects"][0]["position"] is not None and report["defects"][0]["layer"] == 1


async def test_arc_loss_in_layer_3_latches_a_fault_and_the_build_completes_after_reset(tmp_path: Path) -> None:
    job = shorten(small_job(n_layers=4), range(0, 2))
    async with Cell(tmp_path, scale=4) as c:
        c.ctl.open_job(job_from_dict(job))
        build = asyncio.ensure_future(c.ctl.start())
        await c.wait_for(lambda s: s.layer == 2 and s.pass_ == 1 and s.state == "running_depositing", 60)
        await asyncio.sleep(0.1)
        c.harness.call(c.harness.sim("power_source").inject, "arc_loss", duration_s=0.5)
        res = await asyncio.wait_for(build, 10)
        assert res.state == "fault" and c.ctl.machine.state is State.FAULT
        trip = c.ctl.interlocks.trips[0]
        assert "arc" in trip.message.lower() and (trip.layer, trip.pass_) == (2, 1)
        await c.ctl.reset()
        res = await c.ctl.start()
        report = json.loads(c.ctl.write_report(plots=False).read_text())
    assert res.state == "complete" and report["layers_done"] == 4 and report["passes_done"] == 8
    defect = report["defects"][0]
    assert defect["layer"] == 2 and defect["pass"] == 1 and "arc" in defect["message"].lower()
    x, y, z = defect["position"]
    assert abs(z - 3.0) < 0.01 and 4.9 <= x <= 15.1 and 4.9 <= y <= 15.1  # on the inner square of layer 3
    # the arc went out for a while: that stretch is the defect; everything else is there once,
    # but for the re-arc overlap (at most one 2 mm weld move; the deposit log rounds to 1 µm)
    cov = coverage(planned(job), read_segments(c.log / "deposit.jsonl"))
    assert cov.excess_mm <= 2.0 + 0.01 and cov.missing_mm < 15.0, cov.as_dict()

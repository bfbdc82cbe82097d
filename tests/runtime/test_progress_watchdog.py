"""Issue 26 item 2: the progress watchdog, against the simulators (no mocks).

A robot that accepts moves but executes none (seeded fault `freeze@move=N`: RUN, no EXE) and a
CNC that reports Run without moving are faults within the progress timeout, the arc dropped
first (weld start 0 in the power-source simulator's own record before the hold reaches the
device); a normal build never trips it.
"""
from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from bench._coverage import coverage, read_segments
from controller.harness.cell import open_cell
from controller.harness.sim import SimHarness
from controller.job.read import job_from_dict
from controller.runtime.progress import longest_move_s, progress_timeout_s, wall_bound_s
from core.config import load_sim
from tests.cells import Cell, cnc_cell, on_the_cnc_block, planned, small_job
from controller.defaults import SIM_REPLY_TIMEOUT_MS

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

SCALE = 5.0


def _power_log(harness: SimHarness) -> list[dict]:
    sim = harness.sim("power_source")
    return harness.call(lambda: list(sim.log))


def _arc_events(log: list[dict]) -> tuple[dict, dict | None]:
    """The first weld-start drop of a lit arc (arc -> burnback) and the arc going out after it."""
    drop = next(e for e in log if e["event"] == "phase" and e["frm"] == "arc" and e["to"] == "burnback")
    out = next((e for e in log if e["event"] == "phase" and e["frm"] == "burnback" and e["t"] >= drop["t"]), None)
    return drop, out


def test_the_bound_is_the_longest_move_twice_plus_one_second() -> None:
    job = small_job(n_layers=1)
    # 20 mm sides cut into 2 mm moves at 600 mm/min: 0.2 s each
    assert abs(longest_move_s(job_from_dict(job), 2.0) - 0.2) < 1e-9
    assert abs(progress_timeout_s(job_from_dict(job), 2.0, None) - 1.4) < 1e-9
    assert progress_timeout_s(job_from_dict(job), 2.0, 3.0) == 3.0
    assert abs(wall_bound_s(1.4, 5.0) - 0.28) < 1e-9
    assert wall_bound_s(1.4, 120.0) == 0.25                 # the wall floor
    assert wall_bound_s(1.4, 5.0, status_period_s=0.2) == 0.5  # a 5 Hz status needs 2.5 periods


async def test_a_robot_that_stops_executing_trips_within_the_bound_arc_first(tmp_path: Path) -> None:
    job = small_job(n_layers=1)
    bound_process = progress_timeout_s(job_from_dict(job), 2.0, None)
    async with Cell(tmp_path, scale=SCALE, faults="freeze@move=20") as c:
        c.ctl.open_job(job_from_dict(job))
        res = await asyncio.wait_for(c.ctl.start(), 30)
        await asyncio.sleep(0.3)
        log = _power_log(c.harness)
        robot = c.harness.sim("robot")
        held_at = c.harness.call(lambda: robot.held_at)
        trips = list(c.ctl.interlocks.trips)
        alarms = c.ctl.journal.query("SELECT message, layer, pass FROM events WHERE kind='alarm'")
    assert res.state == "fault", res
    msg = trips[0].message
    assert msg.startswith("robot made no progress for ") and "layer 0 pass 0 point " in msg, msg
    assert "arc dropped, motion held" in msg and alarms[0][0] == msg and alarms[0][1:] == (0, 0)
    drop, out = _arc_events(log)
    # arc first: the source saw weld start 0 before the robot got !HOLD
    assert held_at is not None and drop["t"] < held_at, (drop, held_at)
    # the torch stood from its last move's end (the deposit log) to the drop: within the bound
    segs = read_segments(c.log / "deposit.jsonl")
    last_motion = max(s["t1"] for s in segs)
    stood = drop["t_sim"] - last_motion
    assert 0 < stood <= bound_process, (stood, bound_process)
    # and the arc was out (burn-back over) no later than one burn-back after that
    assert out is not None and out["t_sim"] - last_motion <= bound_process + 0.1 * SCALE / SCALE + 0.1
    # no deposit after the stall: nothing at one spot, nothing beyond the last executed move
    assert all(s["t1"] <= drop["t_sim"] + 1e-6 for s in segs)


async def test_a_cnc_that_reports_run_without_moving_trips_within_the_bound_arc_first(tmp_path: Path) -> None:
    cfg = cnc_cell(SCALE)
    job = on_the_cnc_block(small_job(n_layers=1))
    bound_process = progress_timeout_s(job_from_dict(job), 2.0, None)
    async with open_cell(cfg, sim=load_sim(), log_dir=tmp_path / "log", faults="freeze@move=30",
                         runs_dir=tmp_path / "runs", reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        harness = ctl.simulators
        ctl.open_job(job_from_dict(job))
        res = await asyncio.wait_for(ctl.start(), 30)
        await asyncio.sleep(0.5)
        log = _power_log(harness)
        cnc = harness.sim("cnc")
        hold_t = harness.call(lambda: (cnc.machine.hold_t, cnc.machine.spindle_on, cnc.state))
        msg = ctl.interlocks.trips[0].message
    assert res.state == "fault", res
    assert msg.startswith("cnc made no progress for ") and "status Run" in msg and "layer 0 pass 0" in msg, msg
    drop, _out = _arc_events(log)
    # arc first: weld start 0 at the source before the feed hold reached the firmware
    assert hold_t[0] is not None and drop["t_sim"] <= hold_t[0], (drop, hold_t)
    assert hold_t[1] is False  # and the process (M3) is off
    segs = [s for s in read_segments(tmp_path / "log" / "deposit.jsonl") if s["device"] == "cnc"]
    stood = drop["t_sim"] - max(s["t1"] for s in segs)
    # a grbl status comes at <= 5 Hz: the bound has that floor (wall_bound_s)
    bound_wall = wall_bound_s(bound_process, SCALE, 0.2)
    assert 0 < stood <= bound_wall * SCALE, (stood, bound_wall * SCALE)


async def test_a_normal_build_never_trips_the_watchdog(tmp_path: Path) -> None:
    job = small_job(n_layers=2)
    async with Cell(tmp_path, scale=20) as c:
        c.ctl.open_job(job_from_dict(job))
        res = await c.ctl.start()
        dog = c.ctl.runner.passes.watchdog if c.ctl.runner else None
    assert res.state == "complete", res
    assert dog is not None and dog.stood_s is None
    cov = coverage(planned(job), read_segments(c.log / "deposit.jsonl"))
    assert cov.missing_mm < 0.05 and cov.excess_mm < 0.05, cov.as_dict()

"""Issue 38 item 1: the progress watchdog in every motion state, against the simulators (no mocks).

Seeded simulator faults stop a device in each motion state: a robot that takes its travel moves,
says RUN and executes none (`freeze@move=N` right after a bead), a CNC that reports Run without
moving on its travel, a probe move that never ends (`freeze@probe=1`), a homing cycle that never
ends (`freeze@home=1`). Each is a fault within its state's bound naming the device, the state and
how long it stood; no hang; weld start is off at the power source and the CNC's own status report
shows the spindle/laser off and the motion held.
"""
from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from controller.align.routine import cad_mesh, plan_for_mesh
from controller.api import align_at
from controller.harness.align_sim import CNC_MODULE
from controller.harness.cell import open_cell
from controller.harness.sim import SimHarness
from controller.job.read import job_from_dict
from controller.motion.watch import StallFault
from core.config import load_cell, load_sim
from tests.cells import Cell, cnc_cell, on_the_cnc_block, small_job
from controller.defaults import SIM_REPLY_TIMEOUT_MS

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

SCALE = 5.0


def _power_state(harness: SimHarness) -> tuple[bool, str]:
    """The power source simulator's own view: the weld start bit it was last sent, its phase."""
    sim = harness.sim("power_source")
    return harness.call(lambda: (bool(sim.cmd.bits.get("weld_start")), str(sim.phase)))


async def test_a_robot_that_stops_in_travel_is_a_fault_naming_travel(tmp_path: Path) -> None:
    job = small_job(n_layers=1)
    # the first bead's travel is two MOVJ (above the start, down to it); it freezes at the third
    async with Cell(tmp_path, scale=SCALE, faults="freeze@travel=3") as c:
        c.ctl.open_job(job_from_dict(job))
        t0 = time.monotonic()
        res = await asyncio.wait_for(c.ctl.start(), 30)
        took = time.monotonic() - t0
        robot = c.harness.sim("robot")
        held, robot_state = c.harness.call(lambda: (robot.held_at, robot.state))
        weld_start, phase = _power_state(c.harness)
        status = await c.ctl.devices.robot_link().status() if c.ctl.devices else None
        msg = c.ctl.interlocks.trips[0].message
        runner = c.ctl.runner
    assert res.state == "fault" and res.passes_done == 1, res
    assert msg.startswith("robot made no progress for ") and " in travel " in msg, msg
    assert "layer 0 pass 1, travel to its start" in msg and "motion held, weld start dropped" in msg, msg
    stood = float(msg.split("for ", 1)[1].split(" s", 1)[0])
    assert runner is not None and runner.passes.progress_s <= 60
    assert held is not None and robot_state == "HOLD" and status is not None and status.state == "HOLD"
    assert not weld_start and phase in ("idle", "postflow"), (weld_start, phase)
    assert stood < 10 and took < 20, (stood, took)


async def test_a_cnc_that_stands_in_run_on_its_travel_is_a_fault_with_the_spindle_off(tmp_path: Path) -> None:
    cfg = cnc_cell(SCALE)
    job = on_the_cnc_block(small_job(n_layers=1))
    async with open_cell(cfg, sim=load_sim(), log_dir=tmp_path / "log", faults="freeze@travel=3",
                         runs_dir=tmp_path / "runs", reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        harness = ctl.simulators
        ctl.open_job(job_from_dict(job))
        res = await asyncio.wait_for(ctl.start(), 30)
        cnc = harness.sim("cnc")
        sim_state = harness.call(lambda: (cnc.machine.spindle_on, cnc.state))
        weld_start, phase = _power_state(harness)
        link = ctl.devices.cnc if ctl.devices else None
        report = await link.status() if link is not None else None
        msg = ctl.interlocks.trips[0].message
    assert res.state == "fault" and res.passes_done == 1, res
    assert msg.startswith("cnc made no progress for ") and " in travel " in msg and "status Run" in msg, msg
    assert "spindle and laser off" in msg and "layer 0 pass 1" in msg, msg
    assert sim_state[0] is False and not weld_start, (sim_state, weld_start, phase)
    # the firmware's own status report: no spindle/laser power, not running
    assert report is not None and report.spindle == 0 and report.state != "Run", report


def _align_cell(time_scale: float = 10.0):
    cell = load_cell()
    return cell.model_copy(update={"cell": cell.cell.model_copy(update={"time_scale": time_scale})})


async def _align_until_stall(faults: str, time_scale: float = 10.0) -> tuple[str, float, tuple]:
    """`cell align run`'s routine against a CNC simulator seeded with `faults`: the StallFault's
    message, how long the routine took (wall) and the simulator's own state after it."""
    cell = _align_cell(time_scale)
    sim_cfg = load_sim().model_copy(update={"faults": faults})
    plan = plan_for_mesh(cad_mesh(sim_cfg.cnc.workpiece))

    # the CNC's simulator alone, in this process (controller/harness/cell.py), the routine on its link
    async with open_cell(cell, sim=sim_cfg, faults=faults, modules=[CNC_MODULE], connect=False) as ctl:
        sims = ctl.simulators
        assert sims is not None
        t0 = time.monotonic()
        with pytest.raises(StallFault) as err:
            await asyncio.wait_for(align_at(ctl.cfg.devices.cnc.url, cell, plan), 30)
        took = time.monotonic() - t0
        sim = sims.sim("cnc")
        state = sims.call(lambda: (sim.machine.spindle_on, sim.state, sim.machine.homing, sim.status_line()))
    return str(err.value), took, state


async def test_a_probe_move_that_never_ends_is_a_fault_naming_probing() -> None:
    msg, took, (spindle, state, _homing, report) = await _align_until_stall("freeze@probe=1")
    assert msg.startswith("cnc made no progress for ") and " in probing " in msg, msg
    assert "probe point top[0], fast touch" in msg and "motion held, spindle and laser off" in msg, msg
    # the bound: 20 mm of probe travel at the fast feed, × 2 + 1 s, at time scale 10
    cell = _align_cell()
    bound = 2 * cell.probe.travel_mm / (cell.probe.fast_feed_mm_min / 60) + 1
    assert f"progress timeout {bound:.2f} s of process time" in msg, msg
    stood = float(msg.split("for ", 1)[1].split(" s", 1)[0])
    assert stood <= max(bound / 10, 0.5) + 0.3 and took < 15, (stood, took)
    # the firmware's own report: nothing running, no spindle/laser power
    assert spindle is False and state != "Run" and "|FS:" in report and report.split("|FS:")[1].split(",")[1].startswith("0"), report


async def test_a_homing_cycle_that_never_ends_is_a_fault_naming_homing() -> None:
    # the machine's settings plan the cycle: 1000 mm of travel at the 500 mm/min seek, 1 mm pull-off
    # located at 25 mm/min: 125.04 s, × 2 + 1 s = 251.08 s of process time, 2.51 s at time scale 100
    msg, took, (spindle, state, homing, _report) = await _align_until_stall("freeze@home=1", 100.0)
    assert msg.startswith("cnc made no progress for ") and " in homing " in msg, msg
    assert "progress timeout 251.08 s of process time from $130-$132" in msg, msg
    assert "motion held, spindle and laser off" in msg, msg
    assert took < 10 and homing is False and spindle is False, (took, state)


async def test_a_robot_that_stops_mid_bead_drops_the_arc_and_holds(tmp_path: Path) -> None:
    job = small_job(n_layers=1)
    async with Cell(tmp_path, scale=SCALE, faults="freeze@move=20") as c:
        c.ctl.open_job(job_from_dict(job))
        res = await asyncio.wait_for(c.ctl.start(), 30)
        await asyncio.sleep(0.3)   # the burn-back and post-flow run out at the source
        weld_start, phase = _power_state(c.harness)
        status = await c.ctl.devices.robot_link().status() if c.ctl.devices else None
        msg = c.ctl.interlocks.trips[0].message
        snap = c.ctl.snapshot()
    assert res.state == "fault" and " with the arc on " in msg and "arc dropped, motion held" in msg, msg
    assert "layer 0 pass 0 point " in msg, msg
    assert not weld_start and phase in ("idle", "postflow"), (weld_start, phase)
    assert status is not None and status.state == "HOLD" and snap.state == "fault"

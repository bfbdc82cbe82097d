"""Machining under the progress watch (issue 36, docs/contract.md §6): a CNC that stops moving in
the middle of a milling program is a fault within the program's bound, after the safe stop with
the spindle verified off in the status report; a program that runs is never tripped."""
from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
import trimesh

from controller.harness.align_sim import CNC_MODULE
from controller.harness.cell import open_cell
from controller.motion.mill import program_bound_s, program_lines, run_program
from controller.motion.watch import StallFault
from core.config import load_cell, load_sim
from drivers.grbl import CncLink
from planner.dropcutter import ToolShape
from planner.finish import Cut, Surface, plan_finish

pytestmark = pytest.mark.realtime  # a CNC simulator on the wall clock (tests/conftest.py)
SCALE = 50.0


def _program() -> list[str]:
    """A finishing raster 12 × 6 mm with the flat8, 10 mm above the simulator's block (top z = 0)."""
    box = trimesh.creation.box(extents=(20, 20, 10))
    box.apply_translation((0, 0, -5))
    plan = plan_finish(np.asarray(box.triangles), Surface(np.full((20, 30), 0.1), (-8.0, -6.0), 0.5),
                       (-6.0, -3.0, 6.0, 3.0), Cut("flat8", ToolShape("flat", 4.0), 1.0, 1.0, 900.0),
                       finish_stock_mm=0.2, clearance_mm=0.5)
    up = np.eye(4)
    up[2, 3] = 10.0
    return program_lines(plan, up, load_cell().tools.cutters["flat8"], spindle_up_s=0.5)


async def _on_sim(faults: str | None, body):
    cell = load_cell()
    cell = cell.model_copy(update={"cell": cell.cell.model_copy(update={"time_scale": SCALE})})
    sim_cfg = load_sim().model_copy(update={"faults": faults})

    # the CNC's simulator alone, in this process (controller/harness/cell.py), its link driven here
    async with open_cell(cell, sim=sim_cfg, faults=faults or "", modules=[CNC_MODULE], connect=False) as ctl:
        sims = ctl.simulators
        assert sims is not None
        link = CncLink(ctl.cfg.devices.cnc.url, line_scale=SCALE)
        await link.connect()
        try:
            if not link.homed:
                await link.home()
            return await body(link, sims)
        finally:
            await link.close()


def _spindle_on(sims) -> bool:
    """The CNC simulator's own spindle/laser state, read on its loop."""
    cnc = sims.sim("cnc")
    return bool(sims.call(lambda: cnc.machine.spindle_on))


async def test_a_cnc_that_stops_moving_mid_program_is_a_fault_naming_machining() -> None:
    lines = _program()
    bound = program_bound_s(lines)
    assert bound == pytest.approx(2.0)        # twice the spindle's 0.5 s dwell + 1 s

    async def body(link, sims):
        t0 = time.monotonic()
        with pytest.raises(StallFault) as err:
            await asyncio.wait_for(run_program(link, lines), 30)
        st = await link.status()
        return str(err.value), time.monotonic() - t0, _spindle_on(sims), st

    # the simulator reports Run with lines queued and stops moving once 12 blocks ran (mid-raster)
    msg, took, spindle, st = await _on_sim("freeze@move=12", body)
    assert msg.startswith("cnc made no progress for ") and " in machining " in msg, msg
    assert "progress timeout 2.00 s of process time" in msg and "motion held, spindle and laser off" in msg, msg
    stood = float(msg.split("for ", 1)[1].split(" s", 1)[0])
    assert stood <= max(bound / SCALE, 0.5) + 0.3 and took < 15, (stood, took, msg)   # the hold times out on a frozen machine: the reset
    # the firmware's own status report after the stop: nothing running, the spindle off
    assert spindle is False and st.state != "Run" and st.spindle == 0 and not st.spindle_on, st


async def test_a_milling_program_that_runs_is_not_tripped_and_ends_with_the_spindle_off() -> None:
    lines = _program()

    async def body(link, sims):
        wall = await run_program(link, lines)
        return wall, _spindle_on(sims), await link.status()

    wall, spindle, st = await _on_sim(None, body)
    assert wall > 0 and spindle is False and st.state == "Idle" and st.spindle == 0, st

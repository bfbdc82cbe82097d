"""The CNC simulator cuts (sims/cnc/cut.py): a cutter in the spindle takes metal off the workpiece's
height map, logged in cut.jsonl; the touch probe reads the cut; a cut with the spindle stopped is a
tool breakage alarm. Driven over its serial bytes by the grbl driver."""
from __future__ import annotations

import json
import math

import pytest

from core.config import Workpiece as WorkpieceConfig, load_cell
from controller.motion.mill import pause
from drivers.grbl import CncLink, GrblAlarm, GrblError
from sims.clock import SimClock
from sims.cnc import CncSim
from sims.workpiece import Workpiece
from tests.cnc_fixtures import cnc_link


@pytest.fixture
async def mill(tmp_path):
    tools = load_cell().tools
    piece = Workpiece.from_config(WorkpieceConfig(size_mm=(40.0, 40.0, 20.0)), 0.0, seed=3)
    sim = CncSim(clock=SimClock(200.0), workpiece=piece, log_path=tmp_path / "cnc.jsonl",
                 homing_enabled=False, tools=tools)
    async with cnc_link(sim) as link:
        await link.connect()
        yield link, tmp_path / "cut.jsonl"


async def _load(link: CncLink, tool: int) -> None:
    """grbl 1.1h: the programmed pause, the operator's tool, cycle start."""
    await pause(link, f"T{tool} M0 (MSG,load T{tool})")


async def test_a_turning_ball_cutter_cuts_a_slot_the_probe_then_reads(mill):
    link, cut_log = mill
    await link.laser_mode(False)
    assert "$32=0" in await link.command("$$")
    await _load(link, 1)                                   # ball6: 6 mm ball, 12000 rpm
    await link.stream(["G43.1 Z0", "M3 S12000", "G0 Z5", "G0 X-28 Y0", "G1 Z-0.5 F600", "G1 X28 F900",
                       "G0 Z5", "M5"])
    rows = [json.loads(s) for s in cut_log.read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["line"] == "G1X28F900" and rows[0]["tool"] == 1
    seg = 9 * math.acos(2.5 / 3) - 2.5 * math.sqrt(3 * 3 - 2.5 ** 2)   # the ball's section 0.5 deep
    assert rows[0]["removed_mm3"] == pytest.approx(seg * 40, rel=0.06)
    assert rows[0]["depth_mm"] == pytest.approx(0.5, abs=0.02)     # at the 0.5 mm cells' centres
    await _load(link, 0)                                   # the head and its touch probe
    got = await link.probe((0.0, 0.0, -3.0), 100)
    assert got.contact and got.position[2] == pytest.approx(-0.5, abs=0.02)   # the slot's floor
    await link.command("G0 Z5")
    await link.command("G0 Y10")
    got = await link.probe((0.0, 10.0, -3.0), 100)
    assert got.contact and got.position[2] == pytest.approx(0.0, abs=0.02)    # the intact top beside it


async def test_cutting_with_the_spindle_stopped_is_a_tool_breakage_alarm(mill):
    link, cut_log = mill
    await link.laser_mode(False)
    await _load(link, 1)
    with pytest.raises((GrblAlarm, GrblError)):
        await link.stream(["G0 Z5", "G0 X-28 Y0", "G1 Z-0.5 F600", "G1 X28 F900"])   # no M3
    assert link.alarms[-1] == 1 and (await link.status()).state == "Alarm"
    assert not cut_log.exists() or not cut_log.read_text().strip()   # nothing was cut

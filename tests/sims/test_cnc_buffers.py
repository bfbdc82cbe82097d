"""The CNC simulator's buffers are the firmware's it stands for, and it says so in `$I` (issue 38):
a 5-axis machine runs grblHAL, whose RX ring is 1024 bytes, not grbl 1.1h's 128 (bench/five_axis.py)."""
from __future__ import annotations

import re
from pathlib import Path

from core.config import Workpiece as WorkpieceConfig
from sims.clock import SimClock
from sims.cnc import CncSim
from sims.workpiece import Workpiece
from sims.world import World
from tests.cnc_fixtures import cnc_link


async def _stream_to(tmp_path: Path, sim_rx: int, cell_rx: int) -> tuple[list[str], int, int]:
    """`$I` of a simulator with an RX ring of `sim_rx` bytes, the driver's window (cell.yaml says
    `cell_rx`) and the most bytes it had in flight streaming 60 short moves at time scale 1 (the
    planner fills, then the ring)."""
    sim = CncSim(clock=SimClock(1.0), world=World(tmp_path), rx_buffer_bytes=sim_rx,
                 workpiece=Workpiece.from_config(WorkpieceConfig(), 0.0, seed=1), log_path=tmp_path / "cnc.jsonl")
    async with cnc_link(sim, rx_buffer_bytes=cell_rx) as link:
        await link.connect()
        await link.home()
        info = await link.command("$I")
        res = await link.stream(["G91 G1 F3000"] + [f"X{0.2 if k % 2 else -0.2} Y0.01" for k in range(60)] + ["G90"])
        return info, link.capacity, res.max_in_flight_bytes


async def test_a_grblhal_sized_buffer_is_reported_and_filled(tmp_path: Path) -> None:
    info, window, most = await _stream_to(tmp_path, sim_rx=1024, cell_rx=1024)
    opt = next(t for t in info if t.startswith("[OPT:"))
    assert re.match(r"\[OPT:\w+,15,1024\]", opt), opt       # its planner blocks, its RX ring
    assert window == 1023
    assert most > 127          # more lines in flight than grbl 1.1h's ring could hold


async def test_the_driver_never_sends_more_than_the_firmware_says_it_holds(tmp_path: Path) -> None:
    # cell.yaml says 1024 but the controller is a grbl 1.1h (`$I`: 128): its ring is the limit
    info, window, most = await _stream_to(tmp_path, sim_rx=128, cell_rx=1024)
    assert any(t.startswith("[OPT:") and t.endswith(",15,128]") for t in info), info
    assert window == 127 and most <= 127

"""A robot that floods, lies, garbles or goes mute (issue 13), over the real RLP/1 bytes.

The simulator (sims/robot_sim.py with sims/robot_lies.py) is served on an ephemeral loopback
TCP port behind the 115200-baud fault channel; RobotLink talks to it as to a real robot. Each
misbehaviour must end in a latched fault or a lost link within 5 s, with the robot held, and
the moves the link reports executed must be the ones the robot logged.
"""
from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import pytest

from drivers.errors import DeviceError, LinkLost
from drivers.robot import RobotLink
from sims.clock import SimClock
from sims.faults import parse_fault_spec
from sims.robot_sim import RobotSim
from sims.transport import SerialServer

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


class Cell:
    """The robot simulator with a misbehaviour spec, served on loopback TCP."""

    def __init__(self, tmp_path: Path, spec: str, time_scale: float = 20.0) -> None:
        self.log = tmp_path / "robot.jsonl"
        self.faults = tmp_path / "faults.jsonl"
        fs = parse_fault_spec(spec)
        self.sim = RobotSim(clock=SimClock(time_scale), queue_slots=64, log_path=self.log,
                            workspace=((-500, -500, -10), (500, 500, 500)), faults=fs,
                            fault_log=self.faults, line_rate=11520.0)
        self.server = SerialServer(self.sim, name="robot", spec=parse_fault_spec(""), baud=115200)

    async def __aenter__(self) -> "Cell":
        self.sim.start()
        self.url = await self.server.start(None, ephemeral=True)
        return self

    async def __aexit__(self, *exc) -> None:
        await self.server.close()
        await self.sim.close()

    def executed(self) -> list[int]:
        if not self.log.exists():
            return []
        return [json.loads(x)["seq"] for x in self.log.read_text().splitlines()]

    def started(self, mode: str) -> float:
        rows = [json.loads(x) for x in self.faults.read_text().splitlines()]
        return next(r["t_mono"] for r in rows if r["fault"] == mode)


def moves(n: int) -> list[tuple]:
    return [("MOVL", float(i % 20), float(i // 20), 2.0, 0, 0, 1, 600) for i in range(n)]


async def stream_until_trouble(link: RobotLink, n: int, budget_s: float = 12.0) -> tuple[str, float]:
    """Send n moves and wait for the last; return (what stopped it, monotonic time)."""
    errs: list[tuple[str, float]] = []
    link.on_event(lambda ev: errs.append((ev.kind, ev.t)) if ev.kind in ("ERR", "link_lost") else None)

    async def go() -> None:
        last = 0
        for m in moves(n):
            last = await link.send_move(*m)
        await link.wait_executed(last)

    try:
        await asyncio.wait_for(go(), budget_s)
        return "completed", time.monotonic()
    except (DeviceError, LinkLost, asyncio.TimeoutError) as exc:
        kind = type(exc).__name__
        t = errs[0][1] if errs else time.monotonic()
        return kind, t


async def test_heartbeat_flood_is_a_protocol_fault_within_5s(tmp_path):
    async with Cell(tmp_path, "flood@move=20") as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        what, t = await stream_until_trouble(link, 400)
        assert what != "completed"
        assert link.protocol_fault and "flood" in link.protocol_fault
        assert t - cell.started("flood") < 5.0
        assert link.stats.heartbeats > 20
        await asyncio.sleep(0.3)
        assert cell.sim.state == "HOLD"          # the link held the robot itself
        # the link never reported more executed than the robot logged
        assert link.last_exec_ticket <= len(cell.executed())
        await link.close()


async def test_ack_and_exe_of_an_unsent_seq_is_a_protocol_fault(tmp_path):
    async with Cell(tmp_path, "lie@move=30") as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        what, t = await stream_until_trouble(link, 400)
        assert what == "DeviceError"
        assert link.protocol_fault is not None
        assert t - cell.started("lie") < 5.0
        await asyncio.sleep(0.3)
        assert cell.sim.state == "HOLD"
        assert len(cell.executed()) < 400
        await link.close()


@pytest.mark.parametrize("after", [12, 40])
async def test_a_lie_about_a_frame_on_the_line_is_taken_back_from_the_account(tmp_path, after):
    # the robot ACKs and EXEs the seq after its last received one, which the host has already
    # sent (still on the line while the queue fills): it passes as true until the robot's real
    # EXE goes backwards. The account (EXE minus RETRACT) must end where the robot's log ends
    async with Cell(tmp_path, f"lie@move={after}") as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        evs: list[tuple[str, int]] = []
        link.on_event(lambda ev: evs.append((ev.kind, ev.ticket)) if ev.kind in ("EXE", "RETRACT") else None)
        await link.connect()
        what, _ = await stream_until_trouble(link, 400)
        await asyncio.sleep(0.5)                  # held: the last real EXEs are in
        assert what == "DeviceError" and "out of order" in (link.protocol_fault or ""), link.protocol_fault
        claimed = 0
        for kind, tk in evs:
            claimed = tk if kind == "RETRACT" else max(claimed, tk)
        assert claimed == len(cell.executed()) < 400
        await link.close()


async def test_lie_between_builds_is_caught_before_any_motion(tmp_path):
    async with Cell(tmp_path, "lie=0") as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        await asyncio.sleep(1.2)                  # the robot lies about seq 0001 while idle
        assert link.protocol_fault is not None and "never sent" in link.protocol_fault
        with pytest.raises(DeviceError, match="protocol fault"):  # no move goes out while latched
            await asyncio.wait_for(link.send_move(*moves(1)[0]), 0.5)
        assert cell.executed() == []
        await link.close()


async def test_garbled_replies_are_a_protocol_fault_long_before_3s(tmp_path):
    async with Cell(tmp_path, "garble@move=20", time_scale=2.0) as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        what, t = await stream_until_trouble(link, 400)
        assert what == "DeviceError" and "garbled" in (link.protocol_fault or "")
        assert t - cell.started("garble") < 5.0
        assert link.stats.crc_errors >= 10          # garbage kept coming: it never counted as heard
        await asyncio.sleep(0.3)
        assert cell.sim.state == "HOLD"             # the robot still hears the host's !HOLD
        assert len(cell.executed()) < 400
        await link.close()


async def test_a_mute_robot_is_held_then_lost_after_3s(tmp_path):
    async with Cell(tmp_path, "mute@move=20", time_scale=2.0) as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        what, t = await stream_until_trouble(link, 400)
        assert what == "LinkLost"
        assert 2.5 < t - cell.started("mute") < 5.0  # 3 s without a valid frame
        # held at once after 0.75 s of quiet with moves outstanding: it did not run on blind
        assert link.held_at is not None and link.held_at - cell.started("mute") < 1.5
        assert cell.sim.state == "HOLD" and len(cell.executed()) < 400
        await link.close()


async def test_abort_with_40_moves_queued_leaves_the_link_usable(tmp_path):
    async with Cell(tmp_path, "") as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        await link.send_move("WAIT")
        for m in moves(40):
            await link.send_move(*m)
        await link.drain(timeout=5)
        assert cell.sim.state == "WAIT" and len(cell.sim.queue) == 41
        t0 = time.monotonic()
        st = await link.abort()
        assert st.state == "IDLE" and st.queue_free == 64
        last = 0
        for m in moves(5):
            last = await link.send_move(*m)
        await link.wait_executed(last, timeout=5)
        assert time.monotonic() - t0 < 5.0
        assert len(cell.executed()) == 5
        await link.close()


async def test_reset_after_a_protocol_fault_clears_it(tmp_path):
    async with Cell(tmp_path, "lie@t=0.2s") as cell:
        link = RobotLink(cell.url, auto_reconnect=False)
        await link.connect()
        await asyncio.sleep(0.8)
        assert link.protocol_fault is not None
        cell.sim.lies.when.clear()                # the robot is repaired
        cell.sim.lies.started.clear()
        st = await link.reset()
        assert link.protocol_fault is None and st.state == "IDLE"
        last = await link.send_move(*moves(1)[0])
        await link.wait_executed(last, timeout=5)
        await link.close()

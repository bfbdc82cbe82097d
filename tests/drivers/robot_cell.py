"""A robot simulator and its link over a real transport, and the exactly-once yardstick."""
from __future__ import annotations

import json
from pathlib import Path

from drivers.robot import RobotLink
from sims.clock import SimClock
from sims.faults import parse_fault_spec
from sims.robot_sim import RobotSim
from sims.transport import SerialServer
from sims.world import World


class Cell:
    """A robot simulator served on loopback TCP (or a pty), with its log in tmp_path."""

    def __init__(self, tmp_path: Path, *, spec: str = "", time_scale: float = 200.0, pty: bool = False,
                 slots: int = 64, world: World | None = None, **kw) -> None:
        self.log = tmp_path / "robot.jsonl"
        self.sim = RobotSim(clock=SimClock(time_scale), queue_slots=slots, log_path=self.log, world=world,
                            workspace=((-500, -500, -10), (500, 500, 500)), **kw)
        self.server = SerialServer(self.sim, name="robot", spec=parse_fault_spec(spec))
        self.pty = pty

    async def __aenter__(self) -> "Cell":
        self.sim.start()
        self.url = await self.server.start(None, ephemeral=True, pty=self.pty)
        return self

    async def __aexit__(self, *exc) -> None:
        await self.server.close()
        await self.sim.close()

    def executed(self) -> list[dict]:
        return [json.loads(x) for x in self.log.read_text().splitlines()]


def plan(n: int, z: float = 2.0) -> list[tuple]:
    """A zigzag layer of n moves of 1 mm."""
    return [("MOVL", float(i % 50) if (i // 50) % 2 == 0 else float(49 - i % 50), float(i // 50), z, 0, 0, 1, 1500)
            for i in range(n)]


async def run_moves(link: RobotLink, moves: list[tuple]) -> list[int]:
    tickets = [await link.send_move(*m) for m in moves]
    await link.wait_executed(tickets[-1], timeout=60)
    return tickets


def assert_exactly_once(executed: list[dict], moves: list[tuple], first_seq: int = 1) -> None:
    assert [e["seq"] for e in executed] == [(first_seq + i) & 0xFFFF for i in range(len(moves))]
    assert [tuple(e["target"]) for e in executed] == [m[1:4] for m in moves]


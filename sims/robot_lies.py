"""A robot that misbehaves on the wire (issue 13): flood, lie, garble, mute.

Each mode comes from the seeded fault spec (sims/faults.py) as `name@t=T` (wall seconds since
the simulator started), `name@move=N` (once N queue entries were executed) or a bare `name=0`
(at once); `freeze@travel=N` at the N-th travel move (MOVJ) to reach the head of the queue.
Once started a mode stays on:

- flood:  valid `HB n` frames, as many as ~90 % of the line carries (20,000/s unthrottled);
- lie:    `ACK` and `EXE` of the sequence number after the last received one (never sent),
          every 0.5 s;
- garble: every reply goes out with a wrong CRC;
- mute:   no reply at all (the robot still executes what it has).

When a mode starts, one line `{"device": "robot", "fault", "t" (epoch s), "t_mono", "moves"}` is
appended to `faults.jsonl` in the simulator's log directory: the bench measures from there.
"""
from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Protocol

from sims.faults import FaultSpec
from wire import rlp


class Misbehaving(Protocol):
    """What the modes read of the robot simulator (robot_sim.py: RobotSim) and how they write to its line."""

    last_rx: int
    slots: int
    executed_count: int
    travels: int

    def write_raw(self, data: bytes) -> None: ...

MODES = ("flood", "lie", "garble", "mute", "freeze")
LIE_PERIOD_S = 0.5
FLOOD_TICK_S = 0.01
FLOOD_UNTHROTTLED_PER_S = 20000


class Misbehaviour:
    """The misbehaviour modes of one RobotSim; falsy when the spec names none."""

    def __init__(self, sim: Misbehaving, spec: FaultSpec | None, log_path: str | Path | None, line_rate: float | None) -> None:
        self.sim = sim
        self.when: dict[str, tuple[str, float]] = {}
        if spec is not None:
            for name in MODES:
                if name in spec.values:
                    self.when[name] = ("t", 0.0)
                for cond, v in spec.events(name):
                    if cond in ("t", "move", "travel"):
                        self.when[name] = (cond, float(v))
        self.log_path = Path(log_path) if log_path else None
        self.line_rate = line_rate
        self.started: dict[str, float] = {}   # mode -> time.monotonic() it started
        self.t0 = time.monotonic()
        self.flooded = 0
        self.lies_told = 0

    def __bool__(self) -> bool:
        return bool(self.when)

    def active(self, name: str) -> bool:
        """True once mode `name` has started (and records its start the first time)."""
        if name in self.started:
            return True
        w = self.when.get(name)
        if w is None:
            return False
        cond, v = w
        on = (time.monotonic() - self.t0 >= v if cond == "t" else self.sim.executed_count >= v if cond == "move"
              else self.sim.travels >= v)
        if on:
            self.started[name] = time.monotonic()
            self._log(name)
        return on

    def _log(self, name: str) -> None:
        if self.log_path is None:
            return
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "a", encoding="utf-8") as f:
            f.write(json.dumps({"device": "robot", "fault": name, "t": time.time(),
                                "t_mono": time.monotonic(), "moves": self.sim.executed_count}) + "\n")

    def outgoing(self, body: str) -> bytes:
        """The bytes a reply goes out as (b"" when muted)."""
        if self.active("mute"):
            return b""
        data = rlp.encode(body)
        if self.active("garble"):
            good = rlp.crc(body)
            bad = f"{(int(good, 16) ^ 0x1) & 0xFFFFFFFF:08X}"
            data = body.encode("ascii") + b" *" + bad.encode("ascii") + b"\n"
        return data

    async def run(self) -> None:
        """Background: the flood and the lies."""
        next_lie = 0.0
        n = 0
        while True:
            await asyncio.sleep(FLOOD_TICK_S)
            if self.active("flood"):
                per_s = (0.9 * self.line_rate / 19.0) if self.line_rate else FLOOD_UNTHROTTLED_PER_S
                k = max(1, int(per_s * FLOOD_TICK_S))
                frames = []
                for _ in range(k):
                    n += 1
                    frames.append(rlp.encode(f"HB {n}"))
                self.flooded += k
                self._raw(b"".join(frames))
            now = time.monotonic()
            if self.active("lie") and now >= next_lie:
                next_lie = now + LIE_PERIOD_S
                seq = rlp.seq_add(self.sim.last_rx, 1)  # the host has not sent this one
                self.lies_told += 1
                self._raw(rlp.encode(rlp.ack(seq, self.sim.slots)) + rlp.encode(rlp.exe(seq)))

    def _raw(self, data: bytes) -> None:
        if not self.active("mute"):
            self.sim.write_raw(data)

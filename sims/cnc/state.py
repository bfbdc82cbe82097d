"""The state the CNC simulator's parts share (docs/architecture.md, "Packages, not friends").

`CncState` is the machine as grbl keeps it: position, alarm / homing / hold, spindle, the parser's
modal state and position, the planner queue, the probe's result. `sim.py` (the serial protocol and
the executor loop), `gcode.py` (the interpreter), `motion.py` (a block moved over simulated time)
and `system.py` (the `$` commands) read and change it through its public fields and methods.
`CncParts` is what those parts use of the simulator besides its state (the clock, the spindle,
the World, the log); `CncSim` satisfies it. No part reads another part's private attributes.
"""
from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from sims.clock import SimClock
from sims.cnc.block import Block, Pos5
from sims.cnc.cut import Spindle
from sims.workpiece import Workpiece
from sims.world import World

__all__ = ["CncState", "CncParts"]


@dataclass
class CncState:
    """One grbl controller's machine state (the simulator's truth)."""

    letters: str                       # XYZAB or XYZAC: the rotary letters of the configured table
    settings: dict[int, float]         # the `$$` listing
    planner_blocks: int
    home: Pos5
    pos: list[float]                   # the machine position now
    gc_pos: list[float]                # the parser's position: where the last queued move ends
    alarm: bool = False
    homing: bool = False
    homed: bool = False
    hold: bool = False
    hold_sub: int = 0                  # Hold:1 decelerating, Hold:0 complete
    hold_t: float | None = None        # simulated time the feed hold began (None: no deceleration)
    hold_v: float = 0.0                # speed at the hold, mm/s
    hold_decel: float = 0.0            # seconds the deceleration takes
    latch: tuple[float, ...] | None = None   # where the stylus touched: still tripped while it stays there
    spindle_on: bool = False
    spindle_ccw: bool = False          # M4: in laser mode the power follows the speed (sims/cnc/laser.py)
    spindle_s: float = 0.0
    speed_mm_min: float = 0.0          # the actual speed of the motion block under way
    probe_pos: Pos5 = (0.0, 0.0, 0.0, 0.0, 0.0)
    probe_ok: bool = False
    tlo: float = 0.0                   # G43.1 Z: the tool length offset in effect
    # the parser's modal state
    motion_mode: str = "G0"
    absolute: bool = True
    inches: bool = False
    feed_rate: float = 0.0
    s_word: float = 0.0
    inverse_time: bool = False         # G93
    queue: deque[Block] = field(default_factory=deque)   # the planner, head first (non-motion lines too)
    motion_in_queue: int = 0
    lines_received: int = 0            # G-code lines read (a block's default sequence number)
    changed: asyncio.Event = field(default_factory=asyncio.Event)   # replaced by each notify()
    work: asyncio.Event = field(default_factory=asyncio.Event)      # set when the executor has work

    def reset_modal(self) -> None:
        self.motion_mode = "G0"
        self.absolute = True
        self.inches = False
        self.feed_rate = 0.0
        self.s_word = 0.0
        self.inverse_time = False

    def notify(self) -> None:
        """Wake every task waiting in `wait_for`."""
        ev, self.changed = self.changed, asyncio.Event()
        ev.set()

    async def wait_for(self, pred: Callable[[], bool]) -> None:
        while not pred():
            await self.changed.wait()

    def current(self) -> Block | None:
        """The motion block at the head of the planner (None: nothing moves)."""
        for b in self.queue:
            if b.motion:
                return b
        return None

    def push(self, b: Block) -> None:
        if b.motion:
            self.motion_in_queue += 1
        self.queue.append(b)
        self.work.set()

    async def sync(self) -> None:
        """Wait until every queued block has executed (grbl's protocol_buffer_synchronize)."""
        await self.wait_for(lambda: not self.queue)


class CncParts(Protocol):
    """What the interpreter, the executor step and the `$` commands use of the simulator."""

    machine: CncState
    clock: SimClock
    spindle: Spindle
    world: World | None
    workpiece: Workpiece | None
    starved: int                       # times the planner ran empty while lines were still arriving

    @property
    def rx_fill(self) -> int: ...
    def send(self, line: str) -> None: ...
    def raise_alarm(self, code: int) -> None: ...
    def log_block(self, b: Block, t: float) -> None: ...
    def probe_tripped(self) -> bool: ...
    async def run_homing(self) -> None: ...

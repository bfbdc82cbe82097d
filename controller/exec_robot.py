"""Robot executor (RLP/1, DESIGN.md §5): per pass `MOVJ` above the start, `MOVJ` to it, `WAIT`,
then the `MOVL`s streamed behind it while the arc starts; `!GO` on motion release.

The weld moves are queued as soon as the travel is, so the robot's queue is full when the arc
releases motion and stays full (`send_move` awaits window space). Each `EXE` of a weld move is
handed to the runner with the point index it reached.
"""
from __future__ import annotations

import asyncio
from typing import Any, Callable

Point = tuple[float, float, float]
AXIS = (0.0, 0.0, 1.0)  # tool axis: vertical torch (3-axis deposition)


class RobotExecutor:
    platform = "robot"

    def __init__(self, link: Any) -> None:
        self.link = link
        self._at_start: int | None = None
        self._weld: dict[int, int] = {}       # ticket -> point index reached by that move
        self._on_exec: Callable[[int, int], None] | None = None
        self._sent_last: int | None = None
        self._all_sent = False
        self.starved = 0                        # queue ran empty inside a bead
        self.exec_count = 0
        self.min_ahead: int | None = None       # fewest weld moves queued ahead at an EXE inside a bead
        self._lost_cbs: list[Callable[[Any], None]] = []
        self.stopped_at: Point | None = None    # where prepare() found the robot stopped (queue flushed)
        self._subscribe()

    def _subscribe(self) -> None:
        self.link.on_event(self._event)

    def _event(self, ev: Any) -> None:
        if ev.kind == "EXE":
            self._exe(int(ev.ticket))
        elif ev.kind == "link_lost":
            for cb in self._lost_cbs:
                cb(ev.text)
        elif ev.kind == "ERR":
            for cb in self._lost_cbs:
                cb(f"robot error {ev.value} {ev.text}")

    def on_link_lost(self, fn: Callable[[Any], None]) -> None:
        """`fn(text)` when the robot link drops or the robot reports an error."""
        self._lost_cbs.append(fn)

    def _exe(self, ticket: int) -> None:
        self.exec_count += 1
        idx = self._weld.get(ticket)
        if idx is None:
            return
        if self._on_exec is not None:
            self._on_exec(ticket, idx)
        if not self._all_sent and self._sent_last is not None:
            ahead = self._sent_last - ticket
            self.min_ahead = ahead if self.min_ahead is None else min(self.min_ahead, ahead)
        # the queue is empty inside a bead when the move just executed was the last one sent
        if ticket == self._sent_last and not self._all_sent:
            self.starved += 1

    async def prepare(self) -> None:
        """Before a run: an empty, released queue (after a crash the robot may hold old moves)."""
        st = await self.link.status()
        if st.state == "FAULT":
            # a robot fault (workspace) needs !RESET; the sequence numbers restart at 0001
            st = await self.link.reset()
        else:
            # flush whatever an earlier run left queued (held by the silence rule or by a trip)
            st = await self.link.abort()
        # after the flush the robot stands still: no torch went further than this (resume caps
        # its estimate of where a crashed bead's arc went out with it)
        self.stopped_at = tuple(float(v) for v in st.pos) if st is not None and st.pos is not None else None

    async def approach(self, p: Point, clearance: float, speed: float) -> None:
        above = (p[0], p[1], p[2] + clearance)
        await self.link.send_move("MOVJ", *above, *AXIS, speed)
        self._at_start = await self.link.send_move("MOVJ", *p, *AXIS, speed)
        await self.link.send_move("WAIT")

    def next_tickets(self, n: int) -> list[int]:
        """The tickets the next `n` moves will get (only this executor sends moves on the link)."""
        first = self.link.next_ticket
        return list(range(first, first + n))

    def queue_weld(self, pts: list[Point], i0: int, speed: float,
                   on_exec: Callable[[int, int], None]) -> "asyncio.Task[int]":
        """Stream MOVL to pts[i0+1:]; the task's result is the last ticket."""
        self._weld = {}
        self._on_exec = on_exec
        self._all_sent = False

        async def stream() -> int:
            last = 0
            for i in range(i0 + 1, len(pts)):
                last = await self.link.send_move("MOVL", *pts[i], *AXIS, speed)
                self._weld[last] = i
                self._sent_last = last
            self._all_sent = True
            return last

        return asyncio.get_running_loop().create_task(stream())

    async def at_start(self) -> None:
        assert self._at_start is not None
        await self.link.wait_executed(self._at_start)

    def release(self) -> None:
        _fire(self.link.go())

    async def weld_done(self, last_ticket: int) -> None:
        await self.link.wait_executed(last_ticket)

    def hold_now(self) -> None:
        """Write `!HOLD` at once (control frames bypass the queue)."""
        _fire(self.link.hold())

    async def held_position(self) -> Point:
        """Where motion stopped: waits for the robot to confirm HOLD (idempotent) and reads it."""
        st = await self.link.hold()
        return tuple(st.pos)

    async def position(self) -> Point | None:
        st = await self.link.status()
        return tuple(st.pos)


def _fire(x: Any) -> None:
    """Run a control coroutine in the background; a failure shows up as a lost link anyway."""
    if asyncio.iscoroutine(x):
        t = asyncio.get_running_loop().create_task(x)
        t.add_done_callback(lambda f: f.cancelled() or f.exception())

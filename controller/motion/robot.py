"""Robot executor (RLP/1, docs/contract.md §5): per pass `MOVJ` above the start, `MOVJ` to it, `WAIT`,
then the `MOVL`s streamed behind it while the arc starts; `!GO` on motion release.

The weld moves are queued as soon as the travel is, so the robot's queue is full when the arc
releases motion and stays full (`send_move` awaits window space). Each `EXE` of a weld move is
handed to the runner with the point index it reached.
"""
from __future__ import annotations

import asyncio
import time
from typing import Awaitable, Callable, Sequence

from controller.motion.post5 import weld_axes
from controller.job.weld_path import move_speed, weld_points
from controller.job.model import CellJob
from controller.ports import RobotLinkPort
from drivers.grbl import SafeStopResult
from drivers.robot import RobotEvent, RobotStatus
from core.errors import InputError

Point = tuple[float, float, float]
AXIS = (0.0, 0.0, 1.0)  # tool axis of a 3-axis pass: vertical torch


class RobotExecutor:
    platform = "robot"

    def __init__(self, link: RobotLinkPort) -> None:
        self.link = link
        self._at_start: int | None = None
        self._weld: dict[int, int] = {}       # ticket -> point index reached by that move
        self._on_exec: Callable[[int, int], None] | None = None
        self._on_retract: Callable[[int, int | None], None] | None = None
        self._sent_last: int | None = None
        self._all_sent = False
        self.starved = 0                        # queue ran empty inside a bead
        self.exec_count = 0
        self.exe_t = 0.0                        # arrival time of the latest EXE (monotonic)
        self.min_ahead: int | None = None       # fewest weld moves queued ahead at an EXE inside a bead
        self._lost_cbs: list[Callable[[str], None]] = []
        self.stopped_at: Point | None = None    # where prepare() found the robot stopped (queue flushed)
        self.record: RobotStatus | None = None  # the robot's STA before prepare() flushed or reset it
        self.ahead: int | None = None           # weld moves left unexecuted at most (None: the window)
        self.go_t = 0.0                         # a robot sets off on !GO, timed by its EXEs (CNC only)
        self.stopping: asyncio.Task[SafeStopResult] | None = None   # a CNC's safe stop; never on a robot
        self.stop_result: SafeStopResult | None = None
        self._axes: dict[tuple[int, int], list[Point]] = {}
        self._cur_axes: list[Point] | None = None  # the planned tool axis per weld point (5-axis)
        self._pts: dict[tuple[int, int], list[Point]] = {}
        self._weld_pts: list[Point] | None = None
        self._subscribe()

    @property
    def robot_link(self) -> RobotLinkPort:
        return self.link

    @property
    def cnc_link(self) -> None:
        return None

    @property
    def robot_record(self) -> RobotStatus | None:
        return self.record

    def weld_points_by_ticket(self) -> dict[int, int]:
        return dict(self._weld)

    def require_job_axes(self, job: CellJob) -> None:
        """A robot carries any tool axis: nothing to refuse."""

    def on_position(self, fn: Callable[[float, float], None]) -> None:
        """Never called: a robot's pace comes from its EXEs (runtime/bead_measure.py)."""

    def on_power(self, fn: Callable[[float, float, float, float], None]) -> None:
        """Never called: the robot's source holds its own power (the bead judge reads the source)."""

    @property
    def power_follows_speed(self) -> None:
        return None

    async def post_job(self, job: CellJob, max_step_mm: float) -> None:
        """The planned tool axis per weld point of every 5-axis pass (`axes`), before any motion."""
        if job.frame == "cad" and job.alignment is None:

            raise InputError("the job is in the CAD frame and carries no alignment: the controller does not know "
                             "where the substrate is; align it (cell align run --job) or plan with --frame substrate")

        self._axes, self._pts = {}, {}
        for li, la in enumerate(job.layers):
            for pi, p in enumerate(la.passes):
                if p.axes is not None:
                    self._axes[(li, pi)] = weld_axes(p.points.tolist(), p.axes.tolist(), max_step_mm)
                    self._pts[(li, pi)] = weld_points(p.points, max_step_mm)

    def use_pass(self, layer: int, pass_: int) -> None:
        self._cur_axes = self._axes.get((layer, pass_))
        self._weld_pts = self._pts.get((layer, pass_))

    def _axis(self, i: int | None) -> Point:
        if self._cur_axes is None or i is None:
            return AXIS
        return self._cur_axes[min(max(i, 0), len(self._cur_axes) - 1)]

    def _subscribe(self) -> None:
        self.link.on_event(self._event)

    def _event(self, ev: RobotEvent) -> None:
        if ev.kind == "EXE" and ev.ticket is not None:
            self.exe_t = ev.t or time.monotonic()
            self._exe(ev.ticket)
        elif ev.kind == "RETRACT" and self._on_retract is not None and ev.ticket is not None:
            # the robot took back executed moves (it lied): the account goes back to its last true one
            tk = ev.ticket
            idx = max((i for t, i in self._weld.items() if t <= tk), default=None)
            self._on_retract(tk, idx)
        elif ev.kind == "link_lost":
            for cb in self._lost_cbs:
                cb(ev.text)
        elif ev.kind == "ERR":
            for cb in self._lost_cbs:
                cb(f"robot error {ev.value} {ev.text}")

    def on_link_lost(self, fn: Callable[[str], None]) -> None:
        """`fn(text)` when the robot link drops or the robot reports an error."""
        self._lost_cbs.append(fn)

    def on_retract(self, fn: Callable[[int, int | None], None]) -> None:
        """`fn(ticket, idx)` when the robot takes back EXEs past `ticket` (idx: the weld point that
        ticket reached in the current bead, None when before it)."""
        self._on_retract = fn

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
        st = self.record = await self.link.status()
        if st.state == "FAULT" or self.link.protocol_fault:
            # a robot fault (workspace) or a latched protocol fault (a robot that lied) needs
            # !RESET; the sequence numbers restart at 0001
            st = await self.link.reset()
        else:
            # flush whatever an earlier run left queued (held by the silence rule or by a trip)
            st = await self.link.abort()
        # after the flush the robot stands still: no torch went further than this (resume caps
        # its estimate of where a crashed bead's arc went out with it)
        self.stopped_at = _xyz(st.pos) if st is not None and st.pos is not None else None

    async def approach(self, p: Point, clearance: float, speed: float) -> None:
        ax = self._axis(self._start_index(p))
        above = (p[0] + ax[0] * clearance, p[1] + ax[1] * clearance, p[2] + ax[2] * clearance)  # along the tool
        await self.link.send_move("MOVJ", *above, *ax, speed)
        self._at_start = await self.link.send_move("MOVJ", *p, *ax, speed)
        await self.link.send_move("WAIT")

    def _start_index(self, p: Point) -> int | None:
        """Index of the weld point nearest the approached start (a resume may start mid-pass)."""
        wp = self._weld_pts
        if self._cur_axes is None or wp is None:
            return None
        return min(range(len(wp)), key=lambda k: sum((a - b) ** 2 for a, b in zip(wp[k], p)))

    def next_tickets(self, n: int) -> list[int]:
        """The tickets the next `n` moves will get (only this executor sends moves on the link)."""
        first = self.link.next_ticket
        return list(range(first, first + n))

    def queue_weld(self, pts: list[Point], i0: int, speed: float | Sequence[float],
                   on_exec: Callable[[int, int], None]) -> "asyncio.Task[int]":
        """Stream MOVL to pts[i0+1:], each at its move's speed (one for all, or one per move:
        cell-job/2); the task's result is the last ticket."""
        self._weld = {}
        self._on_exec = on_exec
        self._all_sent = False

        async def stream() -> int:
            last = 0
            sent: list[int] = []
            for i in range(i0 + 1, len(pts)):
                if self.ahead is not None and len(sent) >= self.ahead:  # runs dry if the host dies
                    await self.link.wait_executed(sent[-self.ahead])
                last = await self.link.send_move("MOVL", *pts[i], *self._axis(i), move_speed(speed, i - 1))
                sent.append(last)
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
        return _xyz(st.pos)

    async def position(self) -> Point | None:
        st = await self.link.status()
        return _xyz(st.pos)

    def reported_position(self) -> None:
        """A robot reports where it is by EXE, not by a status stream (controller/runtime/stop_point.py)."""
        return None


def _xyz(pos: tuple[float, ...]) -> Point:
    """The first three coordinates of a reported position, as a point."""
    return (float(pos[0]), float(pos[1]), float(pos[2]))


def _fire(x: Awaitable[object]) -> None:
    """Run a control coroutine in the background; a failure shows up as a lost link anyway."""
    if asyncio.iscoroutine(x):
        t = asyncio.get_running_loop().create_task(x)
        t.add_done_callback(lambda f: f.cancelled() or f.exception())

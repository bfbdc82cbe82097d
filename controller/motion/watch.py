"""The progress watch of every motion state (docs/contract.md §6; docs/controller.md "Progress watchdog").

A motion device that is driven (travel, approach, homing, probing, machining, depositing) and
stops making progress is a fault within its state's bound, never a silent hang. Progress is any
execution the device reports (robot EXE, the executor's count of them), any change of its own
last executed sequence number, or any change of its reported position beyond `NOISE_MM` (every
axis, so a rotary-only move counts). The device is asked for its status only once it has been
quiet for a quarter of the bound, so a moving device adds no traffic to its link.

The bound is in process seconds, from the plan of the step (twice its planned time plus 1 s);
in wall seconds it is that divided by the time scale, never less than a floor the status path
can resolve (`FLOOR_WALL_S`, and 2.5 status periods for a device that reports at a fixed rate).

On a stall the watch calls its `stop` (weld start dropped and the source's word on it awaited
where a power source is in the loop, then motion held: robot `!HOLD`, CNC feed hold then `M5`
or a soft reset, verified) and raises `StallFault` with one message naming the device, the
state, how long it stood and where.
"""
from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass
from typing import Any, Awaitable, Callable, Sequence, TypeVar

from core.errors import Fault

NOISE_MM = 0.02          # position change that counts as progress (reports carry 3 decimals)
FLOOR_WALL_S = 0.25      # never less than this (wall): a status round trip plus loop jitter
DROP_MARGIN_S = 0.03     # the dropped start reaches the source within 2 bus cycles: decided this early
SAMPLE_TIMEOUT_S = 1.0   # a status request that takes longer is not a sample (the link's own loss rule acts)

T = TypeVar("T")


class StallFault(Fault):
    """A motion device stood for its state's progress bound (process off, motion held)."""


@dataclass
class Sample:
    t: float                     # time.monotonic() when the report was in
    pos: tuple[float, ...]
    last_exec: int | None        # robot: its last executed sequence number
    state: str


def wall_bound_s(process_s: float, time_scale: float, status_period_s: float | None = None) -> float:
    """The bound in wall seconds, with the floor the status path can resolve."""
    floor = FLOOR_WALL_S if status_period_s is None else max(FLOOR_WALL_S, 2.5 * status_period_s)
    return max(process_s / max(time_scale, 1e-9), floor)


def move_bound_s(length_mm: float, speed_mm_min: float) -> float:
    """The plan's bound of a motion step: twice its time at the planned speed, plus 1 s (process s)."""
    return 2.0 * max(length_mm, 0.0) / max(speed_mm_min / 60.0, 1e-9) + 1.0


def path_length(points: Sequence[Sequence[float]]) -> float:
    """Length of a polyline (its first three coordinates)."""
    return sum(math.dist(a[:3], b[:3]) for a, b in zip(points, points[1:]))


def moved(a: Sample, b: Sample) -> bool:
    if a.last_exec is not None and b.last_exec != a.last_exec:
        return True
    return max((abs(x - y) for x, y in zip(a.pos, b.pos)), default=0.0) > NOISE_MM


def fmt_pos(pos: Sequence[float]) -> str:
    return " ".join(f"{v:.3f}" for v in pos)


class MotionWatch:
    """Watches one motion step of one device. `watch()` returns the fault message once the device
    stood for the bound (after `stop`); it never returns while the device progresses.

    `read()` is a fresh status sample, `stop(sample)` makes the cell safe and returns the tail of
    the message (e.g. "arc dropped, motion held"), `progress()` a counter of executions the
    device reported and when the latest came (None: the device reports none)."""

    def __init__(self, *, device: str, state: str, read: Callable[[], Awaitable[Sample]],
                 stop: Callable[[Sample], Awaitable[str]], bound_process_s: float, time_scale: float,
                 status_period_s: float | None = None, where: Callable[[], str] | None = None,
                 progress: Callable[[], tuple[int, float]] | None = None, arc_on: bool = False,
                 waiting_states: tuple[str, ...] = ("Idle",)) -> None:
        self.device, self.state = device, state
        self.read, self.stop, self.progress = read, stop, progress
        self.status_period = status_period_s
        self.bound_process = bound_process_s
        self.time_scale = time_scale
        self.bound = wall_bound_s(bound_process_s, time_scale, status_period_s)
        self.where = where
        self.arc_on = arc_on
        self.period = min(max(self.bound / 4.0, 0.02), 0.5)
        self.samples = 0
        self.stood_s: float | None = None
        self.stopping = False                 # the device stood: the stop is under way
        self.finished = False                 # the step ended first
        # states in which a standing device is not driven (grbl Idle: it waits for the host's next
        # line); with the arc on none, a torch standing with the arc on is a stall whatever it says
        self.waiting_states: tuple[str, ...] = () if arc_on else waiting_states

    async def guard(self, step: Awaitable[T]) -> T:
        """Await `step` under the watch: a stall cancels it and raises StallFault (the cell
        already made safe by `stop`)."""
        self.finished = self.stopping = False   # a watch may guard several steps, one after the other
        w: asyncio.Future[T] = asyncio.ensure_future(step)
        d = asyncio.ensure_future(self.watch())
        both: list[asyncio.Future[Any]] = [w, d]   # a step's result and the watch's message
        try:
            done, _ = await asyncio.wait(both, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:
            w.cancel()
            d.cancel()
            raise
        if w in done and not self.stopping:
            self.finished = True       # the watch decides nothing from now on
            d.cancel()
            await asyncio.wait([d])    # never left running (a lost cancel in wait_for, Python 3.11)
            return w.result()
        # a stall: the step may have failed of the stop itself (a soft reset flushes its line)
        w.cancel()
        raise StallFault(await d)

    def _count(self) -> tuple[int, float]:
        return self.progress() if self.progress is not None else (0, 0.0)

    async def watch(self) -> str:
        t_prog = time.monotonic()
        n_exec = self._count()[0]
        anchor: Sample | None = None
        # decided this early: a sample may take a status period to come (grbl reports at <= 5 Hz)
        # and the source sees weld start 0 within two bus cycles, both inside the bound
        due = self.bound - DROP_MARGIN_S - (self.status_period or 0.0)
        while True:
            # wake at the period, and on time for the decision at t_prog + due
            left = t_prog + due - time.monotonic()
            await asyncio.sleep(max(0.005, min(self.period, left)) if left > 0 else self.period)
            if self.finished:   # the step ended (a cancel that Python 3.11's wait_for lost lands here)
                return ""
            now = time.monotonic()
            n, t_n = self._count()
            if n != n_exec:     # an execution was reported: progress
                n_exec = n
                t_prog = max(t_prog, t_n or now)
                anchor = None
                continue
            if now - t_prog < self.bound / 4.0:
                continue
            try:
                s = await asyncio.wait_for(self.read(), SAMPLE_TIMEOUT_S)
            except Exception:
                continue  # no answer: the link's own loss rule trips the cell
            self.samples += 1
            if self._count()[0] != n_exec:     # executions handled while the status was asked for
                continue
            if anchor is None or moved(anchor, s):
                if anchor is not None:
                    t_prog = s.t
                anchor = s
                continue
            if s.state in self.waiting_states:   # the device waits on the host: not a stall of the device
                anchor = None
                t_prog = s.t
                continue
            if s.t - t_prog >= due and not self.finished:
                self.stood_s, self.stopping = s.t - t_prog, True
                tail = await self.stop(s)
                return self.message(s, tail)

    def message(self, s: Sample, tail: str) -> str:
        stood = self.stood_s or 0.0
        scale = self.time_scale
        proc = f" ({stood * scale:.1f} s of process time)" if abs(scale - 1.0) > 1e-9 else ""
        what = "no EXE, last executed seq " + str(s.last_exec) if s.last_exec is not None else "status " + s.state
        during = "with the arc on" if self.arc_on else f"in {self.state}"
        at = f" at {self.where()}" if self.where is not None else ""
        return (f"{self.device} made no progress for {stood:.2f} s{proc} {during} ({what}, position "
                f"{fmt_pos(s.pos)} unchanged; progress timeout {self.bound_process:.2f} s of process time, "
                f"{self.bound:.2f} s wall){at}: {tail}")

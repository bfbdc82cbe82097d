"""The progress watchdog (DESIGN.md §6 "Every stop is safe", issue 26): a motion device that
makes no progress while the arc is on is a fault within `progress_timeout`, arc dropped first.

Progress is any EXE (robot), any change of the device's own last executed sequence number
(robot `!STATUS`), or any change of its reported position beyond `NOISE_MM` (robot `!STATUS`,
CNC status report: every axis, so a rotary-only move counts). The device is asked for its
status only once it has been quiet (no EXE) for a quarter of the bound, so a normal build adds
no traffic to the link. The bound, in process seconds: cell.yaml `cell.progress_timeout_s`, or by
default the longest planned weld move's time × 2 + 1 s, from the job at build start; in wall
seconds it is that divided by the time scale, never less than a floor the status path can
resolve (`FLOOR_WALL_S`, and 2.5 status periods for a device that reports at a fixed rate).

On a stall the watchdog drops weld start, waits (at most `ARC_CONFIRM_S`) until the power source
has seen the dropped start (two fresh status cycles), then holds motion and returns the fault
message naming the device, the layer/pass/point and how long it stood; the build runner raises
it as the fault that latches the cell (controller/runtime/build.py).
"""
from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass
from typing import Awaitable, Callable, Sequence

from controller.job.model import CellJob
from controller.ports import MotionExecutor, PowerSourcePort
from core.errors import CellError

NOISE_MM = 0.02          # position change that counts as progress (reports carry 3 decimals)
FLOOR_WALL_S = 0.25      # never less than this (wall): a status round trip plus loop jitter
ARC_CONFIRM_S = 0.1      # wait at most this long for the source to show the dropped start
DROP_MARGIN_S = 0.03     # the dropped start reaches the source within 2 bus cycles: decided this early
SAMPLE_TIMEOUT_S = 1.0   # a status request that takes longer is not a sample (the link's own loss rule acts)


def longest_move_s(job: CellJob, max_step_mm: float) -> float:
    """Process seconds of the longest weld move of the job (its polylines subdivided to at most
    `max_step_mm`, as controller/job/weld_path.py does), each at its segment's planned speed."""
    worst = 0.0
    for la in job.layers:
        for p in la.passes:
            pts = p.points.tolist()
            if len(pts) < 2:
                continue
            for a, b, v in zip(pts, pts[1:], (p.speeds() / 60.0).tolist()):
                seg = math.dist(a[:3], b[:3])
                n = max(1, math.ceil(seg / max_step_mm - 1e-9))
                if v > 0:
                    worst = max(worst, seg / n / v)
    return worst


def progress_timeout_s(job: CellJob, max_step_mm: float, configured: float | None) -> float:
    """The bound in process seconds: the configured one, else 2 × the longest move + 1 s."""
    if configured is not None:
        return float(configured)
    return 2.0 * longest_move_s(job, max_step_mm) + 1.0


def wall_bound_s(process_s: float, time_scale: float, status_period_s: float | None = None) -> float:
    """The bound in wall seconds, with the floor the status path can resolve."""
    floor = FLOOR_WALL_S if status_period_s is None else max(FLOOR_WALL_S, 2.5 * status_period_s)
    return max(process_s / max(time_scale, 1e-9), floor)


class StallFault(CellError):
    """A motion device stood with the arc on for the progress timeout (arc dropped, motion held)."""


@dataclass
class Sample:
    t: float                     # time.monotonic() when the report was in
    pos: tuple[float, ...]
    last_exec: int | None        # robot: its last executed sequence number
    state: str


async def sample(ex: MotionExecutor) -> Sample:
    """A fresh status report of the executor's motion device (robot STA or grbl report)."""
    robot, cnc = ex.robot_link, ex.cnc_link
    if robot is not None:
        rs = await robot.status()
        return Sample(time.monotonic(), tuple(float(v) for v in rs.pos), rs.last_exec, rs.state)
    if cnc is None:
        raise CellError("the executor drives no motion device")
    gs = await cnc.status()
    return Sample(time.monotonic(), tuple(float(v) for v in gs.mpos), None, gs.state)


def _moved(a: Sample, b: Sample) -> bool:
    if a.last_exec is not None and b.last_exec != a.last_exec:
        return True
    return max((abs(x - y) for x, y in zip(a.pos, b.pos)), default=0.0) > NOISE_MM


class ProgressWatchdog:
    """Watches one bead from motion release to its last move. `watch()` returns the fault message
    once the device stood for the bound (after dropping the arc and holding motion); it never
    returns while the device progresses (cancel it when the bead ends)."""

    def __init__(self, ex: MotionExecutor, power: PowerSourcePort, *, bound_wall_s: float, bound_process_s: float,
                 time_scale: float, where: Callable[[], str], status_period_s: float | None = None) -> None:
        self.ex, self.power = ex, power
        self.status_period = status_period_s
        self.bound = bound_wall_s
        self.bound_process = bound_process_s
        self.time_scale = time_scale
        self.where = where
        self.period = min(max(bound_wall_s / 4.0, 0.02), 0.5)
        self.samples = 0
        self.stood_s: float | None = None

    @classmethod
    def of(cls, ex: MotionExecutor, power: PowerSourcePort, bound_process_s: float, time_scale: float,
           where: Callable[[], str]) -> "ProgressWatchdog":
        """For a build runner's executor: the wall bound from the process bound and the time
        scale, with the floor of a device that reports at a fixed rate (grbl's status period)."""
        cnc = ex.cnc_link
        period = cnc.status_period if cnc is not None else None
        return cls(ex, power, bound_wall_s=wall_bound_s(bound_process_s, time_scale, period),
                   bound_process_s=bound_process_s, time_scale=time_scale, where=where, status_period_s=period)

    async def guard(self, weld_done: Callable[[int], Awaitable[None]], tickets: Awaitable[int]) -> None:
        """Await a bead's moves (`weld_done(await tickets)`) under the watchdog: a stall cancels
        them and raises StallFault with the message (arc already dropped, motion held)."""
        async def weld() -> None:
            await weld_done(await tickets)

        w, d = asyncio.ensure_future(weld()), asyncio.ensure_future(self.watch())
        try:
            done, _ = await asyncio.wait({w, d}, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:
            w.cancel()
            d.cancel()
            raise
        if w in done:
            d.cancel()
            w.result()
            return
        w.cancel()
        raise StallFault(d.result())

    def _exec_count(self) -> int:
        return self.ex.exec_count

    async def watch(self) -> str:
        t_prog = time.monotonic()
        n_exec = self._exec_count()
        anchor: Sample | None = None
        # decided this early: a sample may take a status period to come (grbl reports at <= 5 Hz)
        # and the source sees weld start 0 within two bus cycles, both inside the bound
        due = self.bound - DROP_MARGIN_S - (self.status_period or 0.0)
        while True:
            # wake at the period, and on time for the decision at t_prog + due
            left = t_prog + due - time.monotonic()
            await asyncio.sleep(max(0.005, min(self.period, left)) if left > 0 else self.period)
            now = time.monotonic()
            if self._exec_count() != n_exec:     # an EXE arrived: progress
                n_exec = self._exec_count()
                t_prog = max(t_prog, self.ex.exe_t or now)
                anchor = None
                continue
            if now - t_prog < self.bound / 4.0:
                continue
            try:
                s = await asyncio.wait_for(sample(self.ex), SAMPLE_TIMEOUT_S)
            except (asyncio.TimeoutError, Exception):
                continue  # no answer: the link's own loss rule trips the cell
            self.samples += 1
            if self._exec_count() != n_exec:     # EXEs handled while the status was asked for
                continue
            if anchor is None or _moved(anchor, s):
                if anchor is not None:
                    t_prog = s.t
                anchor = s
                continue
            if s.t - t_prog >= due:
                self.stood_s = s.t - t_prog
                return await self._stop(s)

    async def _stop(self, s: Sample) -> str:
        """Arc first (weld start 0, seen by the source), then motion held; the fault message."""
        try:
            self.power.drop_all()
        except Exception:
            pass
        try:  # two fresh cycles: the second was written after the drop
            for _ in range(2):
                await asyncio.wait_for(self.power.next_status(), ARC_CONFIRM_S)
        except Exception:
            pass
        try:
            self.ex.hold_now()
        except Exception:
            pass
        dev = self.ex.platform
        dev = {"robot": "robot", "cnc": "cnc"}.get(dev, dev)
        stood = self.stood_s or 0.0
        scale = self.time_scale
        proc = f" ({stood * scale:.1f} s of process time)" if abs(scale - 1.0) > 1e-9 else ""
        what = "no EXE, last executed seq " + str(s.last_exec) if s.last_exec is not None else "status " + s.state
        return (f"{dev} made no progress for {stood:.2f} s{proc} with the arc on ({what}, position "
                f"{_fmt(s.pos)} unchanged; progress timeout {self.bound_process:.2f} s of process time, "
                f"{self.bound:.2f} s wall) at {self.where()}: arc dropped, motion held")


def _fmt(pos: Sequence[float]) -> str:
    return " ".join(f"{v:.3f}" for v in pos)

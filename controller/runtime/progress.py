"""The build runner's progress watchdog (docs/contract.md §6 "Every stop is safe", issues 26 and 38): a
motion device that makes no progress while the arc is on, or in the travel to a bead's start, is
a fault within its bound, weld start dropped first. The watch itself (what counts as progress,
the wall bound and its floor, the message) is controller/motion/watch.py; homing and probing use
it through controller/align/watched.py.

The bound, in process seconds: with the arc on, cell.yaml `cell.progress_timeout_s`, or by
default the longest planned weld move's time × 2 + 1 s, from the job at build start; in travel,
the travel's length at the travel speed × 2 + 1 s (never less than the weld bound).

On a stall the watchdog drops weld start, waits (at most `ARC_CONFIRM_S`) until the power source
has seen the dropped start (two fresh status cycles), then holds motion and returns the fault
message naming the device, the state, the layer/pass/point and how long it stood; the build
runner raises it as the fault that latches the cell (controller/runtime/pass_run.py).
"""
from __future__ import annotations

import asyncio
import math
import time
from typing import Awaitable, Callable, Sequence

from controller.job.model import CellJob
from controller.ports import MotionExecutor, PowerSourcePort
from core.errors import CellError
from controller.motion.watch import MotionWatch, Sample, StallFault, move_bound_s, wall_bound_s

__all__ = ["ProgressWatchdog", "StallFault", "Sample", "longest_move_s", "progress_timeout_s", "travel_bound_s",
           "wall_bound_s"]

ARC_CONFIRM_S = 0.1      # wait at most this long for the source to show the dropped start


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


def travel_bound_s(frm: Sequence[float] | None, to: Sequence[float], clearance_mm: float, speed_mm_min: float,
                   weld_bound_s: float) -> float:
    """The travel's bound: up to the clearance height, across, down to the start (the executors'
    approach), twice its time at the travel speed plus 1 s, never less than the weld bound."""
    if frm is None:
        return weld_bound_s
    length = abs(float(to[2]) + clearance_mm - float(frm[2])) + math.dist(frm[:2], to[:2]) + clearance_mm
    return max(move_bound_s(length, speed_mm_min), weld_bound_s)


def executor_sample(ex: MotionExecutor) -> Callable[[], Awaitable[Sample]]:
    """A fresh status report of the executor's motion device (robot STA or grbl report)."""
    async def read() -> Sample:
        robot, cnc = ex.robot_link, ex.cnc_link
        if robot is not None:
            rs = await robot.status()
            return Sample(time.monotonic(), tuple(float(v) for v in rs.pos), rs.last_exec, rs.state)
        if cnc is None:
            raise CellError("the executor drives no motion device")
        gs = await cnc.status()
        return Sample(time.monotonic(), tuple(float(v) for v in gs.mpos), None, gs.state)
    return read


class ProgressWatchdog(MotionWatch):
    """The watch of a build runner's executor in one state of the build (`depositing` with the
    arc on, `travel` with it off): a stall drops weld start (seen by the source, at most
    `ARC_CONFIRM_S`), then holds motion (robot `!HOLD`; CNC feed hold, then `M5` or a soft reset)."""

    def __init__(self, ex: MotionExecutor, power: PowerSourcePort, *, bound_process_s: float, time_scale: float,
                 where: Callable[[], str], status_period_s: float | None = None, state: str = "depositing") -> None:
        dev = ex.platform
        self.ex, self.power = ex, power
        super().__init__(device=dev, state=state, read=executor_sample(ex), stop=self._stop,
                         bound_process_s=bound_process_s, time_scale=time_scale, status_period_s=status_period_s,
                         where=where, progress=self._exec, arc_on=state == "depositing")

    @classmethod
    def of(cls, ex: MotionExecutor, power: PowerSourcePort, bound_process_s: float, time_scale: float,
           where: Callable[[], str], state: str = "depositing") -> "ProgressWatchdog":
        """For a build runner's executor: the wall bound from the process bound and the time
        scale, with the floor of a device that reports at a fixed rate (grbl's status period)."""
        cnc = ex.cnc_link
        period = cnc.status_period if cnc is not None else None
        return cls(ex, power, bound_process_s=bound_process_s, time_scale=time_scale, where=where,
                   status_period_s=period, state=state)

    def _exec(self) -> tuple[int, float]:
        return self.ex.exec_count, self.ex.exe_t

    async def _stop(self, s: Sample) -> str:
        """Arc first (weld start 0, seen by the source), then motion held."""
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
        if self.arc_on:
            return "arc dropped, motion held"
        off = ", spindle and laser off" if self.device == "cnc" else ""
        return f"motion held, weld start dropped{off}"

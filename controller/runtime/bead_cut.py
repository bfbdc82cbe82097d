"""How far a bead went on after its last executed move when a trip cut it (the arc stays on
until the start drops and the robot holds): measured from where the robot says it held, else
estimated from the time and the planned speed when the robot cannot say (link lost, garbled)."""
from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Sequence

from controller.job.weld_path import Point
from controller.ports import MotionExecutor
from controller.runtime.arc_out import project


@dataclass(frozen=True)
class BeadCut:
    """The cut bead: its weld points, their arc lengths, where its measured length stands."""

    pts: list[Point]
    cum: Sequence[float]
    from_s: float          # arc length already counted (the last EXE, or where the bead re-arced)
    speed_mm_min: float
    time_scale: float


async def run_on_after_trip(ex: MotionExecutor, cut: BeadCut, t_trip: float, t_exe: float) -> tuple[float, str | None]:
    """(mm deposited after the last EXE, a note for the journal when it is an estimate)."""
    try:
        pos = await asyncio.wait_for(ex.held_position(), 1.0)
    except Exception:   # the robot cannot say where it stopped: estimated below
        pos = None
    if pos is not None:
        s = project(cut.pts, cut.cum, pos, cut.from_s)
        return (max(0.0, s - cut.from_s), None) if s is not None else (0.0, None)
    blind = _blind_run_on(ex, cut, t_trip, t_exe)
    return blind, (f"bead cut with the robot unreachable: {blind:.2f} mm after the last executed move "
                   "estimated from the time and the planned speed")


def _blind_run_on(ex: MotionExecutor, cut: BeadCut, t_trip: float, t_exe: float) -> float:
    """The robot went on at the planned speed from the last EXE until it held: it stopped (and the
    deposit with it) when the first !HOLD after the last EXE reached it, timed from when those bytes
    left, else from the link's own hold; never beyond the last weld move it was sent (it may have
    starved on the way)."""
    link = ex.robot_link
    if link is None:  # a CNC stops where its status report says (run_on_after_trip)
        return 0.0
    holds = [t for t in link.hold_tx if t > t_exe]
    held = holds[0] if holds else link.held_at
    t_stop = min(t_trip, held) if held is not None and held > t_exe else t_trip
    sent = link.max_sent
    weld = ex.weld_points_by_ticket()
    n = len(cut.pts)
    reach = max((i for tk, i in weld.items() if sent is not None and tk <= sent), default=n - 1)
    run_on = max(0.0, t_stop - t_exe) * cut.speed_mm_min / 60.0 * cut.time_scale
    return min(run_on, max(0.0, cut.cum[min(reach, n - 1)] - cut.from_s))

"""How far a bead went on after its last executed move when a trip cut it (the arc stays on
until the start drops and the robot holds): measured from where the robot says it held, else
estimated from the time and the planned speed when the robot cannot say (link lost, garbled).
A device that reports its position as it goes (a CNC) also says where the arc went out
(controller/runtime/stop_point.py): that end is journaled for the resume (`held`, stop_mm)."""
from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Sequence

from controller.job.weld_path import Point
from controller.journal.store import Journal
from controller.ports import MotionExecutor
from controller.runtime.arc_out import project
from controller.runtime.stop_point import ArcOutWatch, deposit_end


STOP_WAIT_S = 5.0   # the CNC's safe stop awaited for its held position (grblHAL's simulator took 3.9 s)


@dataclass(frozen=True)
class BeadCut:
    """The cut bead: its weld points, their arc lengths, where its measured length stands."""

    pts: list[Point]
    cum: Sequence[float]
    from_s: float          # arc length already counted (the last EXE, or where the bead re-arced)
    speed_mm_min: float
    time_scale: float


@dataclass(frozen=True)
class CutEnd:
    """What a trip left of a bead: the mm deposited after the last executed move, a note for the
    journal when that is an estimate, and the stop point along the pass when the device said
    where the deposit ended (None: only the journaled progress is known)."""

    more_mm: float
    note: str | None = None
    stop_mm: float | None = None

    def journal(self, journal: Journal, layer: int, pass_: int) -> None:
        """The note (an estimate), and the stop point as a `held` row (the resume re-arcs there)."""
        if self.note:
            journal.event("info", self.note, layer=layer, pass_=pass_)
        if self.stop_mm is not None:
            journal.pass_state(layer, pass_, "held", stop_mm=round(self.stop_mm, 4))


async def run_on_after_trip(ex: MotionExecutor, cut: BeadCut, t_trip: float, t_exe: float,
                            watch: ArcOutWatch | None = None, wait_s: float = 1.0) -> CutEnd:
    """How far the bead went on after the trip (the hold's position, at most `wait_s` away once a
    CNC's safe stop, given up to `STOP_WAIT_S`, has verified it)."""
    stop = ex.stopping
    if stop is not None and not stop.done():   # a slow hold (a firmware's low $120) takes seconds
        await asyncio.wait([stop], timeout=STOP_WAIT_S)
    try:
        pos = await asyncio.wait_for(ex.held_position(), wait_s)
    except Exception:   # the robot cannot say where it stopped: estimated below
        pos = None
    finally:
        if watch is not None:
            watch.close()
    if pos is not None:
        end = deposit_end(cut.pts, cut.cum, cut.from_s, pos, watch)
        s = end if end is not None else project(cut.pts, cut.cum, pos, cut.from_s)
        return CutEnd(max(0.0, s - cut.from_s), None, end) if s is not None else CutEnd(0.0)
    blind = _blind_run_on(ex, cut, t_trip, t_exe)
    return CutEnd(blind, f"bead cut with the robot unreachable: {blind:.2f} mm after the last executed move "
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

"""Where a bead that a trip cut really ends, from the device's own reports (docs/controller.md, "Resume").

A CNC reports no executed line, only where the tool is: its status reports (5 Hz while it welds,
about every 50 ms during the safe stop, drivers/grbl_stop.py). At a trip the weld start drops and
the feed hold decelerates the torch while the arc burns back, so the deposit ends at whichever
comes first: the point where the motion stopped (the held position) or the point where the torch
was when the arc went out.

`ArcOutWatch` is started at the trip. On every power-source cycle that still shows the arc stable
it notes the position of the device's newest report: a point the torch had surely reached with
the arc on (the report was taken before the cycle came in). Once a cycle shows the arc out it
stops. `deposit_end` then takes the lesser of that point and the held position along the pass: a
lower bound of the deposit's end that misses it by at most the travel between two reports while
the arc was still on, so a resume re-arcing there (less `REARC_OVERLAP_MM`) leaves no gap and
lays little twice. A device without a position stream (a robot: it vouches by EXE) gives no
point, and the resume keeps to its journaled progress.
"""
from __future__ import annotations

from typing import Callable, Sequence

from controller.job.weld_path import Point
from controller.journal.store import PassResume
from controller.ports import MotionExecutor, PowerSourcePort
from controller.runtime.arc_out import project
from drivers.power import PowerStatus

# a resume re-arcs this far before the journaled stop point (`held` row, stop_mm): the deposit
# log rounds to 1 µm, and a re-arc that overlaps its crater a little fuses with it
REARC_OVERLAP_MM = 0.3


class ArcOutWatch:
    """From a trip on: the newest reported position while the arc was still stable."""

    def __init__(self, ex: MotionExecutor, power: PowerSourcePort) -> None:
        self.ex = ex
        st = power.status
        self.arc_out = st is None or not st.arc_stable
        self.on_at: Point | None = None if self.arc_out else ex.reported_position()
        self._unsub: Callable[[], None] | None = None
        if not self.arc_out:
            self._unsub = power.subscribe(self._status)

    def _status(self, st: PowerStatus) -> None:
        if self.arc_out:
            return
        if st.arc_stable:
            self.on_at = self.ex.reported_position()
            return
        self.arc_out = True
        self.close()

    def close(self) -> None:
        """Stop watching (idempotent)."""
        unsub, self._unsub = self._unsub, None
        if unsub is not None:
            unsub()


def deposit_end(pts: Sequence[Point], cum: Sequence[float], from_s: float, held: Point | None,
                watch: ArcOutWatch | None) -> float | None:
    """Length along the pass where the deposit surely reached: the lesser of the held position
    and the last position reported with the arc on; None when the device gave no such position
    on the pass (then nothing is known beyond `from_s`)."""
    if watch is None or watch.on_at is None or held is None:
        return None
    s_on = project(pts, cum, watch.on_at, from_s)
    s_held = project(pts, cum, held, from_s)
    if s_on is None or s_held is None:
        return None
    return min(s_on, s_held)


def known_end(s: float, hist: PassResume | None, end: float) -> float:
    """How far along a started pass (of length `end`) its deposit is known to reach: `s` (the last
    point reached with the arc stable), the latest re-arc point, or the stop point the device gave
    at the latest trip less `REARC_OVERLAP_MM`, whichever lies further."""
    if hist is not None and hist.start_mm is not None:
        s = max(s, min(hist.start_mm, end))
    if hist is not None and hist.stop_mm is not None:
        s = max(s, min(hist.stop_mm - REARC_OVERLAP_MM, end))
    return s

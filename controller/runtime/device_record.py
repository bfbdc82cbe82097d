"""Where a bead a crash cut really ends, from the device's own record (docs/contract.md §6, issue 26):
"a resume never re-deposits what the devices' own records show done, and refuses, with what it
knows, when it cannot tell".

While the arc is on, the robot is given at most `dry_lookahead()` weld moves ahead of the last
one it executed: few enough that, if the controller dies, its queue runs dry before the power
source's watchdog (`devices.power_source.watchdog_ms`) drops the arc. The deposit then ends
exactly where the robot stopped, and the robot reports that itself: its position after the
flush, and its last executed sequence number (mapped to the pass's point index through the
journal's write-ahead `moves` rows). Where two moves already outlast the watchdog (slow in wall
time, e.g. real hardware at time scale 1) the window is not narrowed and the re-arc is the
run-on lower bound of arc_out.py, capped by that same record. A record that contradicts the
journal (the robot executed less than the journal saw: reset or power-cycled) or that cannot be
placed on the pass is a refusal before any motion, naming what is known.
"""
from __future__ import annotations

import math
from typing import Sequence

from controller.journal.store import Journal, PassResume
from controller.ports import MotionExecutor
from controller.runtime.arc_out import RunOn, arc_out_lower_bound, project
from core.errors import CellError

Point = tuple[float, float, float]
# the robot's queued motion must end this long before the power source's watchdog drops the arc
# after the controller died (2 bus cycles, a simulator tick, line latency)
DRY_SLACK_S = 0.03
EXACT_RESUME_MAX_SCALE = 20.0   # above this time scale the robot's queue is not narrowed


class ResumeRefused(CellError):
    """The devices' records cannot tell where a cut bead ends: no motion, the message says what is known."""


def dry_lookahead(ex: MotionExecutor, pts: Sequence[Point], i0: int, speed: float, time_scale: float,
                  watchdog_s: float) -> int | None:
    """Weld moves the robot may hold unexecuted so that it runs dry before the source's watchdog
    drops the arc after a crash (set as the executor's `ahead`); None (the whole window) where two
    moves outlast that, or for an executor without the setting (CNC)."""
    if ex.robot_link is None:  # a CNC streams by its buffer: no lookahead setting
        return None
    if time_scale > EXACT_RESUME_MAX_SCALE:
        # the whole watchdog is a few ms of wall time per move here: a queue that short starves
        # on any host hiccup (the torch stands still with the arc on), so the window stays whole
        # and a crash resume falls back to the run-on estimate (docs/controller.md)
        ex.ahead = None
        return None
    n = 0
    if speed > 0 and len(pts) - 1 > i0:
        longest = max(math.dist(a, b) for a, b in zip(pts[i0:], pts[i0 + 1:]))
        move_wall = longest / (speed / 60.0) / time_scale
        n = int((watchdog_s - DRY_SLACK_S) / move_wall) if move_wall > 0 else 0
    ahead = n if n >= 2 else None
    ex.ahead = ahead
    return ahead


def _fmt(pos: Sequence[float] | None) -> str:
    return "?" if pos is None else " ".join(f"{float(v):.3f}" for v in pos[:3])


def device_record(ex: MotionExecutor, journal: Journal, layer: int, pass_: int, run: int, pts: Sequence[Point],
                  cum: Sequence[float], s: float) -> float | None:
    """Where the robot's own record says it stopped along the pass (length), from its position
    after the flush, else its last executed sequence number; ResumeRefused when the record
    contradicts the journal or cannot be placed on the pass. A CNC: its reported position only."""
    stopped = ex.stopped_at
    rec = ex.robot_record
    s_robot = project(pts, cum, stopped, s) if stopped is not None else None
    if rec is None:
        return s_robot
    known = journal.max_progress_ticket() or 0
    last = rec.last_exec_ticket
    where = (f"layer {layer} pass {pass_}: the journal knows the deposit reached {s:.2f} mm of {cum[-1]:.2f} mm "
             f"(ticket {known}) and run {run} died with the arc on")
    if last < known:
        raise ResumeRefused(f"resume refused: the robot reports last executed seq {rec.last_exec} (ticket {last}) "
                            f"at {_fmt(rec.pos)}, before what the journal saw it execute (ticket {known}): it was "
                            f"reset or power-cycled and lost its record, so where the deposit of {where} ends "
                            "cannot be told; inspect the part")
    if s_robot is not None:
        return s_robot
    mv = journal.move_of(last)
    if mv is not None and (mv[0], mv[1]) == (layer, pass_) and mv[3] == "weld":
        return cum[min(mv[2], len(cum) - 1)]
    span = journal.pass_tickets(layer, pass_, run)
    if span is not None and last >= span[1]:
        return cum[-1]  # it executed every weld move of the pass, and went on
    raise ResumeRefused(f"resume refused: the robot stands at {_fmt(rec.pos)}, off {where}, and its last executed "
                        f"seq {rec.last_exec} (ticket {last}) is no weld move of that pass: where the deposit ends "
                        "cannot be told; inspect the part")


def crash_rearc(ex: MotionExecutor, journal: Journal, layer: int, pass_: int, hist: PassResume, pts: Sequence[Point],
                cum: Sequence[float], s: float, speed: float, time_scale: float, run_on: RunOn) -> tuple[float, str]:
    """(re-arc length, journal line) for a bead whose controller died with the arc on; `s` is
    where the journal knows the deposit reached."""
    s_robot = device_record(ex, journal, layer, pass_, hist.run, pts, cum, s)
    dry = bool(hist.ahead) and s_robot is not None
    if dry:
        assert s_robot is not None
        # the robot held at most `ahead` moves: it ran dry before the source's watchdog dropped
        # the arc, so the deposit ends where its own record says it stopped
        s_new = min(max(s, s_robot - run_on.margin_mm), cum[-1])
    else:
        scale = journal.run_time_scale(hist.run) or time_scale
        s_new = arc_out_lower_bound(s, speed, scale, run_on, s_robot, cum[-1])
    robot = "?" if s_robot is None else f"{s_robot:.2f}"
    return s_new, (f"resume: arc of run {hist.run} went out at or after {s_new:.2f} mm along the pass (last known "
                   f"{s:.2f} mm, robot stopped at {robot} mm{', ran dry first' if dry else ''})")

"""One pass's execution: travel to its start, arc on, stream the weld moves, arc off, the bead's
record; the layer sequencing around it is controller/runtime/build.py.

Per pass: travel to the start (or to the point where the bead stopped, on resume) → arc start
handshake on the power source → release the motion → stream the weld moves → arc end when the
last weld move is executed. Every weld move executed while the arc is stable is journaled (layer,
pass, point index): that is where a resumed bead re-arcs, so no move is executed twice and none is
skipped. The device callbacks (executed moves, retracted EXEs, power-source samples) land here;
a process control hears them through its hooks (controller/runtime/hooks.py).
"""
from __future__ import annotations

import asyncio
import math
import time
from typing import Callable, Sequence

from controller.job.weld_path import Point, weld_points
from controller.journal.queries import SampleRow
from controller.journal.store import Journal
from controller.ports import ArcControl, CellIOPort, MotionExecutor, PowerSourcePort
from controller.runtime.arc_out import arc_lengths, point_at
from controller.runtime.bead_check import judge
from controller.runtime.bead_cut import BeadCut, run_on_after_trip
from controller.runtime.bead_measure import BeadStats, Pace, follow_pace
from controller.runtime.bead_plan import MovePlan, move_plan
from controller.runtime.device_record import crash_rearc, dry_lookahead
from controller.runtime.events import EventBus
from controller.runtime.hooks import BuildHooks
from controller.runtime.machine import CellMachine
from controller.runtime.progress import ProgressWatchdog, travel_bound_s
from controller.runtime.stop_point import ArcOutWatch, known_end
from controller.runtime.work import BuildOptions, WorkItem
from drivers.power import PowerStatus
from planner.job import Layer, Pass

__all__ = ["PassRunner", "STALE_STATUS_S"]

STALE_STATUS_S = 0.1  # a power-source status older than its watchdog (100 ms) does not vouch for a move


class PassRunner:
    """Deposits passes one at a time (`run`); the state of the bead under way, for the device
    callbacks and the interlocks (`current`, `cur_idx`, `interrupted`)."""

    def __init__(self, *, journal: Journal, machine: CellMachine, bus: EventBus, executor: MotionExecutor,
                 power: PowerSourcePort, cellio: CellIOPort | None, options: BuildOptions, arc: ArcControl,
                 hooks: BuildHooks, progress_s: float, journaled: set[tuple[int, int]]) -> None:
        self.journal, self.m, self.bus = journal, machine, bus
        self.ex, self.power, self.cellio, self.o, self.arc = executor, power, cellio, options, arc
        self.hooks = hooks                    # a process control's seams (controller/runtime/hooks.py)
        self.progress_s = progress_s          # process s standing with the arc on before a stall
        self._journaled = journaled           # passes an earlier run started
        self.arc_starts = 0
        self.defects_new = 0                  # beads of this run not deposited as planned
        self.current: WorkItem | None = None
        self.cur_idx: int | None = None       # last point index reached with the arc stable
        self.closing: asyncio.Task[None] | None = None  # an interrupted bead's close (awaits the held position)
        self.watchdog: ProgressWatchdog | None = None
        self._pass: Pass | None = None        # the pass under way, as built
        self._bead: BeadStats | None = None
        self._pace: Pace | None = None        # the robot's EXE arrivals of the current bead
        self._arc_lit = False
        self._unstable_noted = False
        self._first_pass = True               # the first pass of a run may be the one a crash cut
        self._pts: list[Point] = []           # the current pass's weld points
        self._cum: Sequence[float] = []
        self._start_mm = 0.0
        self._acct_idx = 0                    # the last point index a progress report reached
        self._t_exe = 0.0                     # monotonic time of the last EXE with the arc stable
        self._t_exe_rx = 0.0                  # ... as its bytes arrived (reader thread)
        self._measured_mm = 0.0               # length executed with the arc stable (this bead)
        self._faltered = False                # the arc was not stable at some point of this bead
        self._unstable_since_exe = False
        self._defect_at: Point | None = None  # where the bead first went wrong
        self._plan: MovePlan | None = None    # the current pass's speed and wire feed per weld move
        self._samples: list[SampleRow] = []
        self._last_sample = 0.0
        self._unsub: list[Callable[[], None]] = []
        self._stream: asyncio.Task[int] | None = None
        self._at: Point | None = None          # where the torch stands after the previous bead
        # the CNC's status positions: the bead's pace (a robot's pace comes from its EXEs)
        follow_pace(executor, lambda: self._pace)   # and, under M4, its feed and power (docs/laser-power.md)

    # -- the devices' callbacks, for one run ------------------------------------------------------
    def attach(self) -> None:
        self._unsub.append(self.power.subscribe(self._on_power))
        self.ex.on_retract(self._on_retract)

    def detach(self) -> None:
        """The run's end: the weld stream stopped, the callbacks dropped, the samples journaled."""
        if self._stream is not None and not self._stream.done():
            self._stream.cancel()
        for u in self._unsub:
            u()
        self._flush_samples()

    def temperature(self) -> float | None:
        """The part's temperature from the pyrometer (None: no reading)."""
        if self.cellio is None:
            return None
        try:
            t = self.cellio.part_temperature_c
        except Exception:
            return None
        return None if t is None or math.isnan(t) else float(t)

    # -- one pass ---------------------------------------------------------------------------------
    def _start_point(self, item: WorkItem, pts: list[Point], speed: float) -> tuple[int, Point, float]:
        """(k, P, s): re-arc at P, at length s along the pass, on the move pts[k] -> pts[k + 1].

        From the journal: the last point reached with the arc stable, the latest re-arc point, or
        the stop point a CNC gave at the latest trip (controller/runtime/stop_point.py), whichever
        lies further; when the controller died with the arc on, further still, to a lower bound of
        where the arc went out (controller/runtime/arc_out.py).
        """
        first, self._first_pass = self._first_pass, False
        start_idx = min(item.start_idx, len(pts) - 1)
        if (item.layer, item.pass_) not in self._journaled:  # never started: from its first point
            return start_idx, pts[start_idx], arc_lengths(pts[:start_idx + 1])[-1]
        cum = arc_lengths(pts)
        hist = self.journal.pass_resume(item.layer, item.pass_)
        s = known_end(cum[start_idx], hist, cum[-1])
        if first and hist is not None and hist.state == "arc_on" and not hist.arc_unstable:
            # the controller died while this bead was depositing: the device's record decides
            s, line = crash_rearc(self.ex, self.journal, item.layer, item.pass_, hist, pts, cum, s, speed,
                                  self.o.time_scale, self.o.run_on)
            self.journal.event("info", line, layer=item.layer, pass_=item.pass_)
        if s >= cum[-1] - 1e-6:
            return len(pts) - 1, pts[-1], cum[-1]
        k, pt = point_at(pts, cum, s)
        return k, pt, s

    async def run(self, item: WorkItem, layer: Layer) -> None:
        """Deposit pass `item` of `layer` (as built); returns once the pass is done, raises when it
        is not (a trip, a stall, a device that refused)."""
        la, pa = item.layer, item.pass_
        p = self._pass = layer.passes[pa]
        pts, plan = weld_points(p.points, self.o.max_step_mm), move_plan(p, self.o.max_step_mm)
        speed = plan.speed   # the pass's (length-weighted mean); per weld move in plan.speeds (cell-job/2)
        start_idx, start_pt, start_mm = self._start_point(item, pts, speed)
        self.current, self.cur_idx, self._acct_idx = item, start_idx, start_idx
        self._pts, self._measured_mm, self._faltered, self._defect_at, self._plan = pts, 0.0, False, None, plan
        self._cum, self._start_mm = arc_lengths(pts), start_mm
        self.bus.update(layer=la, pass_=pa, passes_in_layer=len(layer.passes))
        if start_idx >= len(pts) - 1:  # nothing left of this bead (it stopped on its last point)
            return
        # the robot's lookahead: set on the executor, journaled with the arc (device_record.py)
        lookahead = dry_lookahead(self.ex, pts, start_idx, plan.slowest, self.o.time_scale, self.o.run_on.watchdog_s)
        self.ex.use_pass(la, pa)  # the executor's tool axes for this pass
        self.m.send("travel")
        self.journal.pass_state(la, pa, "started", start_idx=start_idx, points=len(pts),
                                start_mm=round(start_mm, 4))
        travel = await self._travel_watch(la, pa, start_pt)
        # approach with the weld moves already queued behind the hold point
        await travel.guard(self.ex.approach(start_pt, self.o.clearance_mm, self.o.travel_speed_mm_min))
        ahead = self.ex.next_tickets(len(pts) - 1 - start_idx)
        if ahead:  # write-ahead: the tickets of this bead's weld moves and the points they reach
            self.journal.moves_sent([(tk, la, pa, start_idx + 1 + k, "weld") for k, tk in enumerate(ahead)])
        tickets = self._stream = self.ex.queue_weld(pts, start_idx, plan.speeds, self._on_exec)
        await travel.guard(self.ex.at_start())  # a stall in travel: StallFault, motion held
        self._at = pts[-1]
        self.m.send("arc_start")
        self.power.set_wire_feed(plan.wfs_at(start_idx))
        await self.arc.start()
        self.arc_starts += 1
        self._arc_lit = True
        self._unstable_noted = False
        self._unstable_since_exe = False
        self._bead = BeadStats(arc_on=time.time())
        self.journal.pass_state(la, pa, "arc_on", idx=start_idx, start_mm=round(start_mm, 4), ahead=lookahead)
        self.bus.update(arc_starts=self.bus.latest.arc_starts + 1, travel_speed_mm_min=speed)
        self.m.send("arc_on")
        self._t_exe = time.monotonic()
        self._pace = Pace(self._t_exe, start_mm, starved=-self.ex.starved, planned_mm_min=speed, power_s=self.ex.power_follows_speed,
                          speed_tol=self.o.bead_tolerance().speed_pct / 100, plan_s=plan.plan_s, plan_t=plan.plan_t)
        self.ex.release()
        self.watchdog = ProgressWatchdog.of(self.ex, self.power, self.progress_s, self.o.time_scale,
                                            lambda: f"layer {la} pass {pa} point {self.cur_idx} of {len(pts) - 1}")
        await self.watchdog.guard(self._weld_done(tickets))  # a stall: StallFault, arc first
        self.m.send("arc_end")
        self._arc_lit = False  # before the arc end: its falling arc-stable is no arc loss
        await self.arc.stop()
        self.bus.update(travel_speed_mm_min=None)
        stats = self._close_bead(la, pa, speed, interrupted=False)
        why = judge(stats or {}, p.current_a, plan.wfs_range(), self.o.bead_tolerance(),
                    self._faltered, planned_speed=speed)
        if why is not None:
            self._defect(la, pa, why)

    async def _weld_done(self, tickets: asyncio.Task[int]) -> None:
        await self.ex.weld_done(await tickets)

    async def _travel_watch(self, la: int, pa: int, to: Point) -> ProgressWatchdog:
        """The travel's watch: its bound from where the torch is (the previous bead's end, else
        the device's report) to the bead's start at the travel speed (controller/runtime/progress.py)."""
        frm = self._at if self._at is not None else await self.ex.position()
        bound = travel_bound_s(frm, to, self.o.clearance_mm, self.o.travel_speed_mm_min, self.progress_s)
        at = f"layer {la} pass {pa}, travel to its start " + " ".join(f"{v:.3f}" for v in to)
        return ProgressWatchdog.of(self.ex, self.power, bound, self.o.time_scale, lambda: at, state="travel")

    def _defect(self, la: int, pa: int, why: str) -> None:
        """A bead that was not deposited as planned: journaled with its position (report, state line)."""
        pos = self._defect_at or (self._pts[self.cur_idx] if self._pts and self.cur_idx is not None else None)
        self.journal.defect(la, pa, why, pos=pos, measured_mm=round(self._measured_mm, 3))
        self.defects_new += 1
        self.journal.event("defect", why, layer=la, pass_=pa, pos=pos)

    def _close_bead(self, la: int, pa: int, speed: float, interrupted: bool) -> dict[str, float | None] | None:
        """The bead's record (journal `beads`); a bead deposited to its end is told to the hooks."""
        b, self._bead = self._bead, None
        if b is None:
            return None
        b.arc_off = time.time()
        # the deposited length is what the robot executed with the arc stable (measured), not the plan's
        length = self._measured_mm
        stats = b.as_dict()
        pace, self._pace = self._pace, None
        if pace is not None:
            pace.starved += self.ex.starved   # starvations inside this bead
            if go := self.ex.go_t:   # a CNC sets off when its first weld line arrives
                pace.set_off(go)
            stats.update(pace.figures(self.o.time_scale, length))
        hi = None
        i_mean, u_mean = stats.get("i_mean"), stats.get("u_mean")
        if i_mean is not None and u_mean is not None:
            # heat input per unit length: η·U·I / v (J/mm, v in mm/s), at the measured travel speed
            v = stats.get("speed_mm_min") or speed
            hi = self.o.arc_efficiency * u_mean * i_mean / (v / 60.0)
        self.journal.bead(la, pa, arc_on=b.arc_on, arc_off=b.arc_off, length_mm=length, speed_mm_min=speed,
                          stats=stats, heat_input_j_mm=hi, interrupted=interrupted)
        if not interrupted and self._pass is not None:
            self.hooks.bead_closed(la, pa, [v[0] for v in b.values], self._pass.wfs_m_min)
        return stats

    # -- callbacks ------------------------------------------------------------------------------
    def _on_exec(self, ticket: int, idx: int) -> None:
        """A weld move ending at point `idx` was executed: journal it if the arc was stable."""
        item = self.current
        st = self.power.status
        faltered, self._unstable_since_exe = self._unstable_since_exe, False
        # a CNC status report may pass several points; a robot's EXE vouches for its own move only
        prev = self._acct_idx if self.ex.platform == "cnc" else idx - 1
        self._acct_idx = max(self._acct_idx, idx)
        if item is None or st is None or not st.arc_stable or not self._arc_lit:
            return
        if time.monotonic() - st.t > STALE_STATUS_S:
            # the source's last word is older than its own watchdog: it may have dropped the arc
            # since; the move is not counted as deposited (never report metal that was not)
            faltered = True
        if not faltered and self._pts and 0 < idx < len(self._pts):
            self._measured_mm += max(0.0, self._cum[idx] - max(self._cum[min(prev, idx)], self._start_mm))
        self._t_exe = time.monotonic()
        if self._plan is not None and self._plan.wfs is not None and self._arc_lit:  # the move now running: its wire feed
            self.power.set_wire_feed(self._plan.wfs_at(idx))
        # when the robot's report arrived (the port's reader thread), else now
        self._t_exe_rx = self.ex.exe_t or self._t_exe
        if self._pace is not None and not faltered and 0 <= idx < len(self._cum):
            self._pace.reached(self._t_exe_rx, self._cum[idx])
        self.cur_idx = idx
        self.journal.progress(ticket, item.layer, item.pass_, idx)

    def _on_retract(self, ticket: int, idx: int | None) -> None:
        """The robot took back EXEs past `ticket`: count, and journal, the bead only up to it."""
        item, back = self.current, self.cur_idx
        if item is None or back is None or not self._pts:
            return
        if (idx := max(item.start_idx, -1 if idx is None else idx)) >= back:   # never before this bead's start
            return
        self._measured_mm = max(0.0, self._measured_mm - (self._cum[back] - max(self._cum[idx], self._start_mm)))
        self.cur_idx = self._acct_idx = idx
        self.journal.retract(item.layer, item.pass_, idx, f"robot took back its EXEs after ticket {ticket}: "
                             f"progress withdrawn from point {back} to {idx}")

    def _arc_sample(self, current_a: float, wfs_m_min: float) -> None:
        """The process control's seam: an arc-stable sample at the last point the device reported."""
        item, idx = self.current, self.cur_idx
        if item is not None and idx is not None and 0 <= idx < len(self._cum):
            self.hooks.arc_sample(item.layer, item.pass_, float(self._cum[idx]), current_a, wfs_m_min)

    def _on_power(self, st: PowerStatus) -> None:
        if self._bead is not None and st.arc_stable and self._arc_lit:  # not the burn-back after weld start drops
            self._bead.add(st.current_a, st.voltage_v, st.wfs_m_min)
            self._arc_sample(float(st.current_a), float(st.wfs_m_min))
        if self._arc_lit and not st.arc_stable:
            self._unstable_since_exe = True
            self._pace.arc_lost(st.t) if self._pace is not None else None  # the falling edge ends the arc time
            if not self._faltered and self._pts and self.cur_idx is not None:
                self._defect_at = self._pts[min(self.cur_idx, len(self._pts) - 1)]
            self._faltered = True
        if self._arc_lit and not st.arc_stable and not self._unstable_noted and self.current is not None:
            # the deposit may have stopped here while the torch moves on: a resume after a crash
            # must not assume the arc ran on (controller/runtime/arc_out.py)
            self._unstable_noted = True
            self.journal.event("arc", "arc unstable while depositing", layer=self.current.layer,
                               pass_=self.current.pass_)
        now = time.monotonic()
        if now - self._last_sample >= self.o.sample_period_s:
            self._last_sample = now
            temp = self.temperature()
            item = self.current
            self._samples.append((time.time(), st.current_a, st.voltage_v, st.wfs_m_min, temp,
                                  item.layer if item else None, item.pass_ if item else None))
            self.bus.update(current_a=st.current_a, voltage_v=st.voltage_v, wfs_m_min=st.wfs_m_min,
                            temperature_c=temp, arc_on=st.arc_stable)
            if len(self._samples) >= 10:
                self._flush_samples()

    def _flush_samples(self) -> None:
        rows, self._samples = self._samples, []
        try:
            self.journal.samples(rows)
        except Exception:
            pass

    # -- interlock side -------------------------------------------------------------------------
    def interrupted(self, message: str) -> None:
        """Called (through the runner) by the interlocks after they held motion and dropped the start."""
        self._arc_lit = False
        item, p = self.current, self._pass
        if item is not None and p is not None and self._bead is not None:
            pts = weld_points(p.points, self.o.max_step_mm)
            try:
                self.closing = asyncio.get_running_loop().create_task(
                    self._close_interrupted(item.layer, item.pass_, pts, p.speed_mm_min))
            except RuntimeError:
                self._close_bead(item.layer, item.pass_, p.speed_mm_min, interrupted=True)
        if item is not None:
            self.journal.pass_state(item.layer, item.pass_, "interrupted", reason=message,
                                    idx=self.cur_idx if self.cur_idx is not None else -1)

    async def _close_interrupted(self, la: int, pa: int, pts: list[Point], speed: float) -> None:
        """Close a bead a trip cut, with the length the torch went on after its last EXE."""
        faltered, idx = self._unstable_since_exe, self.cur_idx
        t_trip, t_exe = time.monotonic(), (self._t_exe_rx or self._t_exe)
        if not faltered and idx is not None and self._pts and len(self._pts) == len(pts):
            cut = BeadCut(pts, self._cum, max(self._cum[idx], self._start_mm), speed, self.o.time_scale)
            end = await run_on_after_trip(self.ex, cut, t_trip, t_exe, ArcOutWatch(self.ex, self.power))
            self._measured_mm += end.more_mm
            end.journal(self.journal, la, pa)   # an estimate's note; where the device said the deposit ended
        self._close_bead(la, pa, speed, interrupted=True)

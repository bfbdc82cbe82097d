"""CNC executor (grbl 1.1, docs/contract.md §5): the robot's sequence with `G4 P0` sync points and M4/M5.

Per pass: `G0` above the start and down to it, `G4 P0` (grbl answers `ok` only once motion has
stopped: the torch is at the start); arc start handshake on the power source; then `M4 S…`
(grbl's dynamic laser power: the power follows the actual speed, docs/laser-power.md),
the `G1` weld moves streamed with character counting, `M5`, and the stream's closing `G4 P0`
marks the last weld move executed. grbl reports no per-line execution, so progress comes from
the status reports (≤ 5 Hz): a point counts as reached once the machine position lies on a
later segment of the bead — conservative, so a resumed bead re-arcs at or before the point
where it stopped (the overlap is bounded by one status period of motion, not by one move).
For the bead's timing each report is also placed along the path and timed as it came off the
wire (`on_position`), and the end by the closing `ok`'s arrival (docs/build-record.md arc_time_s).
"""
from __future__ import annotations

import asyncio
import math
import time
from typing import Callable, Sequence

from controller.ports import CncLinkPort, PowerSourcePort
from controller.motion.kinematics import Trunnion
from controller.motion.cnc5 import Five, check_feed
from controller.job.model import CellJob
from controller.job.weld_path import move_speed
from drivers.grbl import SafeStopResult
from core.errors import CellError
from wire.grbl_protocol import GrblStatus, Pos5

Point = tuple[float, float, float]


def _f(v: float) -> str:
    return f"{v:.3f}"


class CncExecutor:
    platform = "cnc"

    def __init__(self, link: CncLinkPort, power: PowerSourcePort | None = None, spindle_s: int = 1000,
                 trunnion: Trunnion | None = None, dynamic_power: bool = True) -> None:
        self.link = link
        self.five = Five(trunnion)  # 5-axis passes (controller/motion/cnc5.py); inactive for 3-axis jobs
        self.power = power
        self.spindle_s = spindle_s
        self._release = asyncio.Event()
        self.starved = 0
        self.exec_count = 0
        self.min_ahead: int | None = None
        self._lost_cbs: list[Callable[[str], None]] = []
        self._pos_cbs: list[Callable[[float, float], None]] = []
        self._power_cbs: list[Callable[[float, float, float, float], None]] = []
        self.dynamic_power = dynamic_power   # `M4`: the process power follows the actual speed (docs/laser-power.md)
        self.exe_t = 0.0   # when the latest progress (status report, the closing `ok`) came off the wire
        self.go_t = 0.0    # when the current bead's weld lines began to go out (grbl sets off at once)
        self.stopping: asyncio.Task[SafeStopResult] | None = None   # the safe stop of the latest hold_now()
        self.stop_result: SafeStopResult | None = None
        self.ahead: int | None = None      # a robot's lookahead setting; the CNC streams by its buffer
        self.stopped_at: Point | None = None   # a robot's flushed position; the CNC reports its own
        self.accel_mm_s2 = 10.0                     # the hold's deceleration bound (grbl default)

    @property
    def robot_link(self) -> None:
        return None

    @property
    def cnc_link(self) -> CncLinkPort:
        return self.link

    @property
    def robot_record(self) -> None:
        return None

    def weld_points_by_ticket(self) -> dict[int, int]:
        return {}

    def on_link_lost(self, fn: Callable[[str], None]) -> None:
        self._lost_cbs.append(fn)

    def on_retract(self, fn: Callable[[int, int | None], None]) -> None:
        """Never called: the CNC's progress comes from its status reports, which cannot go back."""

    def on_position(self, fn: Callable[[float, float], None]) -> None:
        """`fn(t, s)` for every status report during a weld: at wall time t (as the report came off
        the wire) the tool was s mm along the pass's points (the bead's pace: runtime/bead_measure.py)."""
        self._pos_cbs.append(fn)

    def on_power(self, fn: Callable[[float, float, float, float], None]) -> None:
        """`fn(t, s, feed, power)` for every status report during a weld: its `FS:` feed and power."""
        self._power_cbs.append(fn)

    @property
    def power_follows_speed(self) -> float | None:
        """`M4` (laser mode, $32=1): grbl scales the power S with the actual speed (docs/laser-power.md)."""
        return float(self.spindle_s) if self.dynamic_power else None

    async def prepare(self) -> None:
        st = await self.link.status()
        if st.state.startswith("Alarm"):
            await self.link.unlock()
        elif st.state.startswith("Hold"):
            await self.link.soft_reset()
        await self.link.command("G90 G21 G94")
        await self._laser_mode()
        await self._level_table()

    async def _level_table(self) -> None:
        """The job's A/B leveling, commanded and read back from the status report before any bead."""
        lines = self.five.level_lines()
        if not lines:
            return
        await self.link.stream(lines)  # ends with G4 P0: the table has arrived
        st = await self.link.status()
        level = self.five.level
        if level is not None and not self.five.level_ok(st.mpos):
            raise CellError(f"cnc: the table reports A/B {st.mpos[3]:.4f}/{st.mpos[4]:.4f}°, not the job's "
                            f"leveling {level[0]:.4f}/{level[1]:.4f}°; check the rotary axes")

    async def post_job(self, job: CellJob, max_step_mm: float) -> None:
        """Before any motion: every 5-axis pass to machine axes, or InputError naming the point."""
        self.require_job_axes(job)
        self.five.check_alignment(job, self.link.reset_at)
        if job.alignment is not None and job.alignment.no_level:
            self.five.level = None   # aligned without leveling: the tilt is in the transform, no A/B move
        await self.five.post_job(job, max_step_mm, self.link.baud)
        # the feed check fits every 5-axis pass again: seconds of numpy, off the loop that cycles the devices
        await asyncio.to_thread(check_feed, job, self.five.trunnion, self.link, max_step_mm)

    def require_job_axes(self, job: CellJob) -> None:
        """The firmware's axes against the job, before homing or any motion (docs/contract.md §5):
        GrblAxesMissing (exit 2) naming the firmware and the axes it lacks."""
        why = job_axes_need(job)
        if why is not None:
            self.link.require_axes("XYZ" + self.five.letters[3:5], why)

    def use_pass(self, layer: int, pass_: int) -> None:
        self.five.use(layer, pass_)

    async def _laser_mode(self) -> None:
        """`$32=1` before any M3 (power-up default is 0): in laser mode grbl drops the process
        power on feed hold and between motions; checked by reading it back."""
        await self.link.laser_mode(True)

    async def process_off(self) -> GrblStatus:
        """Process off and motion held: feed hold (laser mode drops S), then confirm `FS:f,0`
        in a status report; a soft reset (which stops the spindle) if power still shows."""
        await self.link.feed_hold()
        st = await self.link.status()
        for _ in range(25):
            if not str(st.state).startswith(("Run", "Hold:1", "Jog")):
                break
            st = await self.link.status()
        if st.spindle != 0:
            await self.link.soft_reset()
            st = await self.link.status()
        return st

    async def approach(self, p: Point, clearance: float, speed: float) -> None:
        if self.five.active:
            await self.link.stream(self.five.approach_lines(p, clearance, speed))
            return
        await self.link.stream([f"G0 Z{_f(p[2] + clearance)}", f"G0 X{_f(p[0])} Y{_f(p[1])}",
                                f"G1 Z{_f(p[2])} F{speed:.0f}"])  # ends with G4 P0: at the start

    def next_tickets(self, n: int) -> list[int] | None:
        return None  # grbl lines carry no sequence numbers

    def queue_weld(self, pts: list[Point], i0: int, speed: float | Sequence[float],
                   on_exec: Callable[[int, int], None]) -> "asyncio.Task[int]":
        self._release = asyncio.Event()
        self.go_t = 0.0
        lines = [f"{'M4' if self.dynamic_power else 'M3'} S{self.spindle_s}"]
        if self.five.active:  # chord-tolerance split moves: the track maps back to the planned points
            lines += self.five.weld_lines(i0, speed)
            track, t0, on_track = self.five.track(i0, on_exec)
        else:
            # F on every line: each move at its own speed (cell-job/2), grbl's F being modal anyway
            lines += [f"G1 X{_f(pts[i][0])} Y{_f(pts[i][1])} Z{_f(pts[i][2])} F{move_speed(speed, i - 1):.0f}"
                      for i in range(i0 + 1, len(pts))]
            track, t0, on_track = pts, i0, on_exec
        lines.append("M5")
        along = _Along(pts, i0, self.five.part_point if self.five.active else _xyz)

        async def run() -> int:
            await self._release.wait()
            poll = asyncio.get_running_loop().create_task(self._track(track, t0, on_track, along))
            self.go_t = time.monotonic()
            try:
                await self.link.stream(lines)
            finally:
                poll.cancel()
            last = len(pts) - 1
            # the closing G4 P0's `ok` as it came off the wire: the last weld move had ended
            self.exe_t = self.link.answer_t or time.monotonic()
            on_exec(last, last)
            self.exec_count += len(lines)
            return last

        return asyncio.get_running_loop().create_task(run())

    async def _track(self, pts: list[Point], i0: int, on_exec: Callable[[int, int], None], along: "_Along") -> None:
        """Progress from the status reports: the points the position has passed, and where along
        the planned path the tool was when the report came off the wire (`on_position`)."""
        k = i0
        while True:
            st = await self.link.status()
            fresh = self.link.latest_status is st
            self.exe_t = self.link.status_t if fresh else 0.0
            self.exe_t = self.exe_t or time.monotonic()
            at = along.locate(st.mpos)
            pos = _xyz(st.mpos)
            for j in range(k, min(k + 200, len(pts) - 1)):
                if _on_segment(pos, pts[j], pts[j + 1]):
                    if j > k:
                        k = j
                        on_exec(j, j)
                    break
            if at is not None:
                for fn in self._pos_cbs:
                    fn(self.exe_t, at)
                for pf in self._power_cbs:
                    pf(self.exe_t, at, st.feed, st.spindle)

    async def at_start(self) -> None:
        return None  # approach() returned after its G4 P0: the torch is there

    def release(self) -> None:
        self._release.set()

    async def weld_done(self, _last: int) -> None:
        return None  # the stream's closing G4 P0 came back: every weld move has executed

    def hold_now(self, reason: str = "hold") -> None:
        """The CNC's safe stop at once (feed hold, then M5 or a soft reset where lines are
        queued, each verified from the next status report): `self.stopping` until verified."""
        if self.stopping is not None and not self.stopping.done():
            return
        self.stopping = asyncio.get_running_loop().create_task(self._safe_stop(reason))
        self.stopping.add_done_callback(lambda f: f.cancelled() or f.exception())

    async def _safe_stop(self, reason: str) -> SafeStopResult:
        """The one call of the CNC stop sequence: CncLink.safe_stop.

        The hold is given the time to decelerate from the reported feed at `accel_mm_s2` (grbl's
        default $120-$122) plus 0.5 s: a firmware still in `Hold:1` after that is not slowing down
        (it reports Run without moving) and is reset, process off, rather than left at M3."""
        st = self.link.latest_status
        feed = st.feed if st is not None else 0.0
        self.stop_result = await self.link.safe_stop(reason, hold_timeout_s=0.5 + feed / 60.0 / self.accel_mm_s2)
        return self.stop_result

    async def held_position(self) -> Point:
        if self.stopping is not None and not self.stopping.done():
            await asyncio.wait([self.stopping], timeout=20.0)
        st = await self.link.status()
        if self.five.active:
            return self.five.part_point(st.mpos)
        return _xyz(st.mpos)

    async def position(self) -> Point | None:
        return await self.held_position()

    def reported_position(self) -> Point | None:
        """The tool tip at the newest status report the link received (part coordinates on a 5-axis pass)."""
        st = self.link.latest_status
        if st is None:
            return None
        return self.five.part_point(st.mpos) if self.five.active else _xyz(st.mpos)


def job_axes_need(job: CellJob) -> str | None:
    """Why the job needs the rotary axes (A/B), None when X/Y/Z do: 5-axis passes, or an
    alignment that levels the table (not one made with `cell align run --no-level`)."""
    if any(p.axes is not None for la in job.layers for p in la.passes):
        return f"job '{job.name}' (5-axis passes with axes)"
    al = job.alignment
    if al is not None and not al.no_level:
        return f"job '{job.name}' (its alignment levels the table with A {al.table_a_deg}°, B {al.table_b_deg}°)"
    return None


def _xyz(pos: tuple[float, ...]) -> Point:
    """X, Y, Z of a reported machine position."""
    return (float(pos[0]), float(pos[1]), float(pos[2]))


class _Along:
    """How far along the planned weld points (mm from the first) a reported position lies, within
    `tol` mm of the path, searching forward from the move the previous report lay on."""

    def __init__(self, pts: list[Point], i0: int, tip: Callable[[Pos5], Point], tol: float = 0.05) -> None:
        self.pts, self.k, self.tip, self.tol = pts, i0, tip, tol
        self.cum = [0.0]
        for a, b in zip(pts, pts[1:]):
            self.cum.append(self.cum[-1] + math.dist(a, b))

    def locate(self, mpos: Pos5) -> float | None:
        p = self.tip(mpos)
        for j in range(self.k, min(self.k + 200, len(self.pts) - 1)):
            f = _fraction(p, self.pts[j], self.pts[j + 1], self.tol)
            if f is not None:
                self.k = j
                return self.cum[j] + f * (self.cum[j + 1] - self.cum[j])
        return None


def _fraction(p: Point, a: Point, b: Point, tol: float) -> float | None:
    """How far along a → b the point nearest p lies (0..1), None when p is off the segment."""
    ab = [y - x for x, y in zip(a, b)]
    L2 = sum(v * v for v in ab)
    if L2 < 1e-12:
        return None
    t = sum((pv - av) * v for pv, av, v in zip(p, a, ab)) / L2
    if t < -1e-6 or t > 1 + 1e-6:
        return None
    t = min(1.0, max(0.0, t))
    return t if math.dist(p, [av + t * v for av, v in zip(a, ab)]) < tol else None


def _on_segment(p: Point, a: Point, b: Point, tol: float = 0.02) -> bool:
    ab = [y - x for x, y in zip(a, b)]
    L2 = sum(v * v for v in ab)
    if L2 < 1e-12:
        return math.dist(p, a) < tol
    t = sum((pv - av) * v for pv, av, v in zip(p, a, ab)) / L2
    if t < 0 or t > 1:
        return False
    q = [av + t * v for av, v in zip(a, ab)]
    return math.dist(p, q) < tol

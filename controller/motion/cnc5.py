"""The CNC executor's 5-axis side: per pass machine axes X Y Z A B|C, approach and G93 weld lines.

Kept apart from exec_cnc.py (its stop/process-off behaviour belongs to the grbl lane). All
passes of a job are post-processed before the first motion (`post_job`), so a point outside the
axis limits refuses the job, naming layer, pass and point, instead of stopping mid-build.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from controller.motion.lines5 import ROUNDING_SHARE, Lines, compact_line, fit_lines, serial_min_s
from controller.motion.post5 import Post5, move_line, weld_axes
from controller.job.weld_path import move_speed, move_values, weld_points, weld_segments
from controller.job.model import CellJob
from core.errors import InputError
from planner.job import Pass
from controller.motion.kinematics import Trunnion
from controller.ports import CncLinkPort
from core.config import CellConfig
import asyncio

Point = tuple[float, float, float]


def _weld_points(points: Sequence[Sequence[float]], max_step_mm: float) -> list[Point]:
    return weld_points(points, max_step_mm)  # the build's own subdivision: indices must agree


def _axes(p: Pass) -> list[list[float]] | None:
    """A pass's planned tool axes as lists (None: a 3-axis pass, vertical torch)."""
    return p.axes.tolist() if p.axes is not None else None


class Five:
    """Machine axes for the job's 5-axis passes; `active` while the current pass is one."""

    def __init__(self, trunnion: Trunnion | None) -> None:
        self.trunnion = trunnion
        self.letters = "XYZA" + (trunnion.table[1] if trunnion is not None else "B")
        self.passes: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.cur: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # per pass the machine moves after the chord-tolerance split: part points, axes, machine
        # axes and the planned (journaled) point each move end lies on or after
        # per pass the machine lines (controller/motion/lines5.py): as long as the chord tolerance
        # lets them be, each at least twice its serial time at the link's baud
        self.fine: dict[tuple[int, int], Lines] = {}
        self.cur_fine: Lines | None = None
        self.baud = 115200
        self._stream: tuple[np.ndarray, np.ndarray] | None = None  # the streamed moves: machine xyz, planned index
        self.start: np.ndarray | None = None   # machine axes of the approached start point
        self.start_part: np.ndarray | None = None
        self.level: tuple[float, float] | None = None  # the job's A/B leveling (its alignment)

    @property
    def active(self) -> bool:
        return self.cur is not None

    def check_alignment(self, job: CellJob, reset_at: float) -> None:
        """The job's alignment drives the table: its A/B leveling, refused when stale or missing."""
        self.level = None
        al = job.alignment
        if al is None:
            if job.frame == "cad":
                raise InputError("the job is in the CAD frame and carries no alignment: the part's pose on the "
                                 "table is unknown; align it first (cell align run --job, or cell repair run)")
            return
        probed = al.probed_at
        if probed is None or probed < reset_at:
            raise InputError("the job's alignment was probed before the CNC's last homing, reset or power-up "
                             "(the table may have moved): align again in this session (cell repair run does both)")
        a, b = al.table_a_deg, al.table_b_deg
        if a is None or b is None:
            raise InputError("job alignment: table_deg a/b (the A/B leveling) missing")
        if any(p.axes is not None for la in job.layers for p in la.passes):
            raise InputError("an aligned 5-axis job is not supported yet: align a 3-axis job "
                             "or plan without --five-axis")
        self.level = (a, b)

    def level_lines(self) -> list[str]:
        """Before the first bead: the table to the job's A/B leveling (clear above, then turn)."""
        if self.level is None:
            return []
        a, b = self.level
        return ["G90 G94", f"G0 {self.letters[3]}{a:.4f} {self.letters[4]}{b:.4f}"]

    @property
    def table(self) -> Trunnion:
        """The configured trunnion (a 5-axis pass cannot be posted without one)."""
        if self.trunnion is None:
            raise InputError("5-axis passes need the table's kinematics (cell.yaml `kinematics:`)")
        return self.trunnion

    def level_ok(self, mpos: Sequence[float]) -> bool:
        return self.level is None or (abs(float(mpos[3]) - self.level[0]) < 0.002
                                      and abs(float(mpos[4]) - self.level[1]) < 0.002)

    async def post_job(self, job: CellJob, max_step_mm: float, baud: int = 115200) -> None:
        """Every pass to machine axes and lines, in a worker thread (nothing computes on the loop
        that cycles the devices: docs/contract.md §6)."""

        self.passes, self.fine, self.baud = {}, {}, baud
        if not any(p.axes is not None for la in job.layers for p in la.passes):
            return
        if self.trunnion is None:
            raise InputError("job has 5-axis passes (axes) but the CNC has no kinematics; "
                             "set kinematics in cell.yaml")
        for li, la in enumerate(job.layers):
            for pi, p in enumerate(la.passes):
                self.passes[(li, pi)], self.fine[(li, pi)] = await asyncio.to_thread(
                    post_pass, self.trunnion, self.letters, baud, p, max_step_mm, f"job layer {li} pass {pi} ")

    def _current(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        assert self.cur is not None, "no 5-axis pass in use: use() it first"
        return self.cur

    def use(self, layer: int, pass_: int) -> None:
        self.cur = self.passes.get((layer, pass_))
        self.cur_fine = self.fine.get((layer, pass_))
        self._stream = None

    def _machine_at(self, p: Point) -> tuple[int, np.ndarray]:
        """Index of the segment start nearest to p and the machine axes at p (a resume may start mid-move)."""
        pts, axes, m = self._current()
        q = np.asarray(p, dtype=float)
        k = int(np.argmin(np.linalg.norm(pts - q, axis=1)))
        if np.linalg.norm(pts[k] - q) < 1e-6:
            return k, m[k]
        k = max(0, min(k, len(pts) - 2))
        ab = pts[k + 1] - pts[k]
        f = float(np.clip((q - pts[k]) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0))
        ax = axes[k] + (axes[k + 1] - axes[k]) * f
        mm = Post5(self.table).machine(q[None, :], ax[None, :] / np.linalg.norm(ax), (m[k, 3], m[k, 4]))
        return k, mm[0]

    def approach_lines(self, p: Point, clearance: float, speed: float) -> list[str]:
        """G94; up; table and XY at the start (rapid); down along the tool axis (machine -Z)."""
        _, m = self._machine_at(p)
        self.start, self.start_part = m, np.asarray(p, dtype=float)
        up = m.copy()
        up[2] += clearance
        return ["G94", f"G0 Z{up[2]:.3f}", move_line(up, self.letters, verb="G0"),
                f"G1 Z{m[2]:.3f} F{speed:.0f}"]

    def weld_lines(self, i0: int, speed: float | Sequence[float]) -> list[str]:
        """G93 inverse-time moves from the approached start to the end of the pass, then G94.

        The moves are the pass's lines (controller/motion/lines5.py); a start that is not a line's
        end (a resume) has the stretch to the next line end fitted afresh. F = 1 / the planned
        minutes of each line, at the speeds of the weld moves it covers (one for the bead, or one
        per weld move: cell-job/2), never shorter than twice its serial time.
        """
        pts, axes, m = self._current()
        fine = self.cur_fine
        post = Post5(self.table)
        seconds = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.maximum(
            [move_speed(speed, k) / 60.0 for k in range(len(pts) - 1)], 1e-9)
        start_part = self.start_part if self.start_part is not None else pts[i0]
        start_m = self.start if self.start is not None else m[i0]
        f = 0.0
        if i0 + 1 < len(pts):
            ab = pts[i0 + 1] - pts[i0]
            f = float(np.clip((start_part - pts[i0]) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0))
        u0 = i0 + f
        if fine is None:
            fine = Lines(pts, axes, m, np.arange(len(pts), dtype=float))
        e = int(np.searchsorted(fine.at, u0 + 1e-9, side="right"))   # the first line end past the start
        head, nxt = _head(post, pts, axes, m, seconds, start_part, start_m, u0, fine, e, self)
        part = np.vstack([head.part, fine.part[nxt:]])
        mach = np.vstack([head.machine, fine.machine[nxt:]])
        at = np.r_[head.at, fine.at[nxt:]]
        lines = Lines(part, np.vstack([head.axes, fine.axes[nxt:]]), mach, at)
        self._stream = (mach[:, :3], lines.seg)
        mins = serial_min_s(self.letters, self.baud)
        t = lines.times(seconds, np.array([mins(a, b) for a, b in zip(mach[:-1], mach[1:])]))
        out = ["G93"]
        for k in range(1, len(mach)):
            out.append(compact_line(mach[k - 1], mach[k], self.letters, 60.0 / float(t[k - 1])))
        return out + ["G94"]

    def machine_xyz(self) -> list[Point]:
        """The machine X Y Z of the streamed moves (after weld_lines): the path the status reports follow."""
        if self._stream is None:
            return [(float(r[0]), float(r[1]), float(r[2])) for r in self._current()[2]]
        return [(float(r[0]), float(r[1]), float(r[2])) for r in self._stream[0]]

    def track(self, i0: int, on_exec: Callable[[int, int], None]) -> tuple[list[Point], int, Callable[[int, int], None]]:
        """For the executor's progress: the streamed path, its first index, and on_exec taking
        indices into it back to the job's planned (journaled) points, each reported once."""
        if self._stream is None:
            return self.machine_xyz(), i0, on_exec
        planned = self._stream[1]
        done = [i0]

        def cb(j: int, _k: int) -> None:
            k = int(planned[min(j, len(planned) - 1)])
            for q in range(done[0] + 1, k + 1):   # a line over several planned points: each once, in order
                on_exec(q, q)
            done[0] = max(done[0], k)

        return self.machine_xyz(), 0, cb

    def part_point(self, mpos: Sequence[float]) -> Point:
        """Where the tool tip is on the part, from a status report's X Y Z A B|C."""
        x, y, z, a, s = (float(v) for v in mpos[:5])
        inv = np.linalg.inv(self.table.matrix(a, s))
        q = inv[:3, :3] @ np.array([x, y, z]) + inv[:3, 3]
        return (float(q[0]), float(q[1]), float(q[2]))


# --- what the CNC link can feed (issue 29, docs/contract.md §6 "Simulated time") ---------------------------
# The simulated serial line keeps its baud in simulated time on both sides (sims/transport.py and
# CncLink(line_scale=time_scale)); what it cannot keep is the host. A bead whose moves are shorter
# than a line's wall cost at the time scale would stand still with the process on between moves,
# which the machine would not: the time scale is limited to what the host can feed, and the build
# says so. The wall cost of a streamed line depends on where the CNC simulator runs
# (docs/controller.md, "Simulated time the host can feed"):
# - in the controller's own interpreter (`cell run --sim`, `cell repair run --sim`): the driver and
#   the simulator share one lock, up to ~2 ms a line (issue 29: 0 gaps at 1.5 ms a line, gaps of
#   0.1 s at 0.9 ms; issue 38, load 11-14: the tube stood still 0.02 s of 20 s at scale 5, its
#   lines 2.1 ms, and 3.2 s at 10, 1.1 ms);
# - in a process of its own (`cell sim up`, `cell tui --sim`, `cell demo`): the controller's share
#   only. bench/five_axis.py --beside, the tube on the grblHAL cell (1024-byte RX ring), load 5.4-6.6
#   on the 2-core host: 0.000 s standing still at scale 10 (1.07 ms of wall time a line), 0.53 s at
#   15 (0.71 ms), 3.08 s at 20 (0.54 ms). 1.0 ms a line: the lowest wall cost measured with no
#   stand-still, and a job whose lines are shorter than that is lowered and told so.
# The check at the build's start (`check_feed`) uses the lower, beside cost: it refuses what no
# topology can feed; the command that starts the simulators chose the scale with its own cost.
HOST_LINE_WALL_S = 2.0e-3
HOST_LINE_BESIDE_S = 1.0e-3
_WINDOW = 8   # moves averaged: the grbl planner (15 blocks) rides over a short burst of shorter ones


@dataclass(frozen=True)
class FeedLimit:
    time_scale: float          # the largest time scale the host can feed every bead at
    link_scale: float          # the same for the serial line at its baud (< 1: it starves on the machine too)
    layer: int
    pass_: int
    move_s: float              # the shortest planned move (process time) of that bead, averaged
    host_line_s: float = HOST_LINE_WALL_S   # the wall time a streamed line was taken to cost

    def message(self, time_scale: float) -> str:
        return (f"cnc: at time scale {time_scale:g} the link cannot feed layer {self.layer} pass {self.pass_} "
                f"(its moves take {self.move_s * 1000:.1f} ms of process time, {self.move_s / time_scale * 1000:.2f} ms "
                f"of wall time; a streamed line takes up to {self.host_line_s * 1000:.1f} ms on this host): the torch "
                f"would stand still with the process on between moves; time scale limited to {self.time_scale:g}")


def _pass_moves(five: Five, post: Post5 | None, p: Pass, max_step_mm: float,
                baud: int = 115200) -> tuple[np.ndarray, np.ndarray]:
    """(process seconds, bytes) per streamed weld line of one pass, as the executor sends them."""
    # mm/s per weld move (each at its segment's speed: cell-job/2)
    speed = np.asarray(move_values(p.speeds(), weld_segments(p.points, max_step_mm))) / 60.0
    pts = np.asarray(_weld_points(p.points.tolist(), max_step_mm))
    if post is not None and p.axes is not None:
        _, lines = post_pass(post.trunnion, five.letters, baud, p, max_step_mm)
        mins = serial_min_s(five.letters, baud)
        m = lines.machine
        seconds = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.maximum(speed, 1e-9)
        t = lines.times(seconds, np.array([mins(a, b) for a, b in zip(m[:-1], m[1:])]))
        nbytes = np.array([len(compact_line(a, b, five.letters, 60.0 / max(float(x), 1e-9))) + 1
                           for a, b, x in zip(m[:-1], m[1:], t)], dtype=float)
        return t, nbytes
    length = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    nbytes = np.array([len(f"G1 X{x:.3f} Y{y:.3f} Z{z:.3f} F{v * 60:.0f}") + 1
                       for (x, y, z), v in zip(pts[1:], speed)], dtype=float)
    return length / np.maximum(speed, 1e-9), nbytes


def post_pass(trunnion: Trunnion, letters: str, baud: int, p: Pass, max_step_mm: float,
              where: str = "") -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], Lines]:
    """One 5-axis pass: its weld points, axes and machine axes, and its lines (InputError naming
    `where` and the point the axis limits cannot reach)."""
    post = Post5(trunnion)
    pts = np.asarray(_weld_points(p.points.tolist(), max_step_mm))
    axes = np.asarray(weld_axes(p.points.tolist(), _axes(p), max_step_mm))
    try:
        m = post.machine(pts, axes)
    except InputError as exc:
        raise InputError(f"{where}{exc}") from None
    speed = np.asarray(move_values(p.speeds(), weld_segments(p.points, max_step_mm))) / 60.0
    tol = trunnion.chord_tolerance_mm * ROUNDING_SHARE
    return (pts, axes, m), fit_lines(post, pts, axes, m, speed, tol, serial_min_s(letters, baud))


def _head(post: Post5, pts: np.ndarray, axes: np.ndarray, m: np.ndarray, seconds: np.ndarray,
          start_part: np.ndarray, start_m: np.ndarray, u0: float, fine: Lines, e: int,
          five: Five) -> tuple[Lines, int]:
    """The lines from a start (a planned point or inside a move) to the pass's line end e, fitted
    afresh over the planned points between; the start alone when it is a line end itself. And the
    index of the pass's first line end after the head."""
    at_end = e > 0 and abs(float(fine.at[e - 1]) - u0) < 1e-9 and float(np.linalg.norm(fine.part[e - 1] - start_part)) < 1e-6
    if at_end or e >= len(fine.at):
        return Lines(start_part[None, :], fine.axes[max(e - 1, 0)][None, :], start_m[None, :], np.array([u0])), e
    end_u = float(fine.at[e])
    k0, k1 = int(np.floor(u0)) + 1, int(np.ceil(end_u - 1e-9))
    inner = np.arange(k0, k1)
    a0 = start_m
    P = np.vstack([start_part, pts[inner], fine.part[e]])
    ax0 = axes[min(int(np.floor(u0)), len(axes) - 1)]
    A = np.vstack([ax0, axes[inner], fine.axes[e]])
    M = np.vstack([a0, m[inner], fine.machine[e]])
    at = np.r_[u0, inner.astype(float), end_u]
    keep = np.r_[True, np.diff(at) > 1e-9]
    P, A, M, at = P[keep], A[keep], M[keep], at[keep]
    sub = Lines(P, A, M, at)
    node_s = sub.times(seconds)
    tol = post.trunnion.chord_tolerance_mm * ROUNDING_SHARE
    fit = fit_lines(post, P, A, M, np.linalg.norm(np.diff(P, axis=0), axis=1) / np.maximum(node_s, 1e-9), tol)
    return Lines(fit.part, fit.axes, fit.machine, np.interp(fit.at, np.arange(len(at)), at)), e + 1


def feed_limit(job: CellJob, trunnion: Trunnion | None, baud: int = 115200, max_step_mm: float = 2.0,
               host_line_s: float = HOST_LINE_WALL_S) -> FeedLimit | None:
    """The largest time scale at which the CNC link can feed every bead of `job` (None: no beads),
    a streamed line taken to cost `host_line_s` of wall time."""
    five = Five(trunnion)
    post = Post5(trunnion) if trunnion is not None else None
    best: FeedLimit | None = None
    for li, la in enumerate(job.layers):
        for pi, p in enumerate(la.passes):
            if len(p.points) < 2:
                continue
            try:
                t, nb = _pass_moves(five, post, p, max_step_mm, baud)
            except InputError:
                continue  # post_job names it before any motion
            if len(t) == 0:
                continue
            w = min(_WINDOW, len(t))
            k = np.ones(w) / w
            tw, bw = np.convolve(t, k, mode="valid"), np.convolve(nb, k, mode="valid")
            i = int(np.argmin(tw))
            host = float(tw[i]) / host_line_s
            link = float((tw / (bw / (baud / 10.0))).min())
            if best is None or host < best.time_scale:
                best = FeedLimit(host, link, li, pi, float(tw[i]), host_line_s)
    if best is None:
        return None
    return FeedLimit(_round_down(best.time_scale), best.link_scale, best.layer, best.pass_, best.move_s, host_line_s)


def _round_down(k: float) -> float:
    """A time scale people can read: 1, 2, 5, 10, 20, 40, 60 … at most k (never below 1)."""
    for v in (1000, 600, 400, 200, 120, 100, 60, 40, 30, 20, 15, 10, 8, 5, 4, 3, 2):
        if v <= k:
            return float(v)
    return 1.0


def limit_time_scale(cfg: CellConfig, job: CellJob, max_step_mm: float = 2.0,
                     beside: bool = False) -> tuple[CellConfig, str | None]:
    """cfg with cell.time_scale lowered to what the CNC link can feed for `job` (CNC cells, simulated
    time only), and the message saying so; (cfg, None) when nothing was lowered. `beside`: the
    simulators run in a process of their own (`cell sim up`), not in this interpreter."""
    if cfg.cell.platform != "cnc" or cfg.cell.time_scale <= 1.0:
        return cfg, None
    lim = feed_limit(job, Trunnion.from_config(cfg.kinematics), cfg.devices.cnc.baud, max_step_mm,
                     HOST_LINE_BESIDE_S if beside else HOST_LINE_WALL_S)
    if lim is None or lim.time_scale >= cfg.cell.time_scale:
        return cfg, None
    msg = lim.message(cfg.cell.time_scale)
    return cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"time_scale": lim.time_scale})}), msg


def check_feed(job: CellJob, trunnion: Trunnion | None, link: CncLinkPort, max_step_mm: float = 2.0) -> None:
    """Before any motion: a simulated link (line_scale > 1) faster than the host can feed the job's
    beads is refused, naming the time scale that can (`limit_time_scale` lowers it where the
    simulators are started here: `cell run --sim`, `cell repair run --sim`, and `cell sim up`'s
    clock). At the lower, beside line cost: the command that started the simulators chose the scale
    for where they run; this refuses what no topology can feed."""
    refuse_unfed(job, trunnion, link.line_scale, link.baud, max_step_mm, beside=True)


def refuse_unfed(job: CellJob, trunnion: Trunnion | None, scale: float, baud: int, max_step_mm: float = 2.0,
                 beside: bool = False) -> None:
    """InputError when simulated time at `scale` is faster than the host can feed the job's beads
    over the CNC link (`beside`: the simulators in a process of their own); needs no device, so a
    command calls it before it connects (docs/controller.md, "Simulated time")."""
    if scale <= 1.0:
        return
    lim = feed_limit(job, trunnion, baud, max_step_mm, HOST_LINE_BESIDE_S if beside else HOST_LINE_WALL_S)
    if lim is not None and scale > lim.time_scale + 1e-9:
        raise InputError(lim.message(scale).replace("; time scale limited to",
                                                    "; run the simulators at time scale")
                         + " or less (cell.yaml cell.time_scale; restart `cell sim up` with it), or give "
                           "--sim to run them here at that scale")

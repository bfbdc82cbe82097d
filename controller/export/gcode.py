"""G-code for grbl 1.1 / grblHAL (docs/contract.md §5, CNC): the program the live CNC executor streams.

Per layer an interpass dwell (`G4 P<s>`, grbl's P is seconds); per pass a travel above the start,
down to it, `M4 S<power>` (process on, grbl's dynamic laser power in laser mode `$32=1`: the power
follows the actual speed, docs/laser-power.md), the `G1` weld moves at the pass's feed, `M5` (process off).
Each pass is headed by a comment carrying its welding parameters, so the file round-trips.
5-axis passes go through the same post-processor and lines as the executor (controller/motion/post5.py,
lines5.py): the same chord tolerance, each line at least twice its serial time at the cell's baud.
Lines stay within grbl's 80-character line buffer.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from controller.motion.kinematics import Trunnion
from controller.export.program import Program, ProgramPass
from controller.motion.lines5 import ROUNDING_SHARE, compact_line, fit_lines, serial_min_s
from controller.motion.post5 import Post5, move_line
from core.errors import InputError

MAX_LINE = 80  # grbl's LINE_BUFFER_SIZE: a longer line is refused (error:14)


def _f(v: float) -> str:
    s = f"{v:.3f}"
    return "0.000" if s == "-0.000" else s


def _pass_comment(p: ProgramPass) -> str:
    return (f"(PASS L{p.layer} P{p.index} {p.role} W{p.width_mm:.3f} I{p.current_a:.2f} "
            f"WFS{p.wfs_m_min:.3f})")


def _five_axis_pass(prog: Program, p: ProgramPass, post: Post5, letters: str, prev: tuple[float, float] | None,
                    clearance_mm: float, travel_mm_min: float, power_s: int,
                    baud: int) -> tuple[list[str], tuple[float, float]]:
    """One pass through the executor's post-processor and lines (controller/motion/lines5.py):
    X Y Z A B|C, as long as the chord tolerance lets each line be and at least twice its serial
    time at `baud`, inverse-time feed (G93)."""
    pts, axes = prog.machine(p) if prog.aligned else (p.points, p.axes)   # the table frame
    table = Post5(post.trunnion)
    try:   # continuous from the last pass where the limits allow, else as the executor (afresh)
        m = table.machine(pts, axes, prev)
    except InputError:
        m = table.machine(pts, axes)
    tol = post.trunnion.chord_tolerance_mm * ROUNDING_SHARE
    speeds = p.segment_speeds() / 60.0   # mm/s per segment
    lines = fit_lines(table, pts, axes, m, speeds, tol, serial_min_s(letters, baud))
    mins = serial_min_s(letters, baud)
    lm = lines.machine
    move_s = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.maximum(speeds, 1e-9)
    t = lines.times(move_s, np.array([mins(a, b) for a, b in zip(lm[:-1], lm[1:])]))
    up = lm[0].copy()
    up[2] += clearance_mm
    out = [_pass_comment(p), "G94", move_line(up, letters, verb="G0"), f"G1 Z{_f(lm[0][2])} F{travel_mm_min:.0f}",
           f"M4 S{power_s}", "G93"]
    out += [compact_line(lm[k - 1], lm[k], letters, 60.0 / float(t[k - 1])) for k in range(1, len(lm))]
    out += ["G94", "M5", f"G0 Z{_f(lm[-1][2] + clearance_mm)}"]
    return out, (float(lm[-1][3]), float(lm[-1][4]))


def write_gcode(prog: Program, *, clearance_mm: float, travel_mm_min: float, power_s: int,
                trunnion: Trunnion | None = None, baud: int = 115200) -> list[str]:
    """The program as G-code lines (no line numbers; grbl answers each with ok).

    A job with tool axes goes through the executor's 5-axis post-processor (controller/motion/post5.py)
    with the table of cell.yaml (`trunnion`); the alignment is then part of that transform."""
    if prog.five_axis and trunnion is None:
        raise InputError("this job has tool axes (a 5-axis plan): give the table kinematics (cell.yaml)")
    post = Post5(trunnion, prog.transform if prog.aligned else None) if prog.five_axis and trunnion else None
    letters = "XYZA" + ("B" if trunnion is not None and trunnion.table == "AB" else "C")
    prev: tuple[float, float] | None = None
    out = [f"(cell export: {prog.name})", f"(job sha256 {prog.sha256[:16]})",
           "(laser mode: set $32=1 before streaming; M4 power follows the speed)", "G21 G90 G94", "M5"]
    if prog.aligned:
        out.append("(alignment applied: points in the machine frame)")
    last_layer: int | None = None
    for p in prog.passes:
        if p.layer != last_layer:
            out.append(f"(LAYER {p.layer})")
            dwell = prog.layer_dwell_s.get(p.layer, 0.0)
            if last_layer is not None and dwell > 0:
                out.append(f"G4 P{dwell:.1f}")
            last_layer = p.layer
        if post is not None:
            lines, prev = _five_axis_pass(prog, p, post, letters, prev, clearance_mm, travel_mm_min, power_s, baud)
            out += lines
            continue
        pts, _ = prog.machine(p)
        x0, y0, z0 = pts[0]
        out += [_pass_comment(p), f"G0 Z{_f(z0 + clearance_mm)}", f"G0 X{_f(x0)} Y{_f(y0)}",
                f"G1 Z{_f(z0)} F{travel_mm_min:.0f}", f"M4 S{power_s}"]
        out += _weld_moves(pts, p)
        out += ["M5", f"G0 Z{_f(pts[-1][2] + clearance_mm)}"]
    out += ["M5", "M30"]
    too_long = [ln for ln in out if len(ln) > MAX_LINE]
    if too_long:
        raise InputError(f"G-code line longer than grbl's {MAX_LINE} characters: {too_long[0]!r}")
    return out


def _weld_moves(pts: np.ndarray, p: ProgramPass) -> list[str]:
    """The G1 weld moves of a 3-axis pass: F on the first, and again on every move whose speed
    differs (F is modal); a wire feed that changes (cell-job/2) as a `(WFS …)` comment before its
    move: grbl has no wire feed, the controller sets it on the power source."""
    out: list[str] = []
    feed = wfs = ""
    for (x, y, z), v, w in zip(pts[1:], p.segment_speeds(), p.segment_wfs()):
        f, wf = f"{v:.1f}", f"{w:.3f}"
        if p.wfs is not None and wf != wfs:
            out.append(f"(WFS{wf})")
        out.append(f"G1 X{_f(x)} Y{_f(y)} Z{_f(z)}" + (f" F{f}" if f != feed else ""))
        feed, wfs = f, wf
    return out


# ---- reading it back --------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class ParsedPass:
    layer: int
    index: int
    role: str
    width_mm: float
    current_a: float
    wfs_m_min: float
    speed_mm_min: float
    points: np.ndarray
    rotary: np.ndarray | None = None   # (n, 2) A and B|C of a 5-axis pass, machine frame
    feeds: np.ndarray | None = None    # F of each weld move (G93: 1/min)
    wfs: np.ndarray | None = None      # the wire feed of each weld move where the program gives it per move


_WORD = re.compile(r"([A-Z])(-?\d+(?:\.\d*)?)")
_PASS = re.compile(r"\(PASS L(\d+) P(\d+) (\w+) W([\d.]+) I([\d.]+) WFS([\d.]+)\)")
_WFS = re.compile(r"\(WFS([\d.]+)\)")


def parse_gcode(lines: list[str]) -> list[ParsedPass]:
    """The passes of an exported program: the points laid with the process on, their feed, and
    (5-axis) the rotary axes; in inverse-time mode the feed is per move (see `feeds`)."""
    reader = _Reader()
    for raw in lines:
        reader.line(raw)
    return reader.out


@dataclass
class _Reader:
    """parse_gcode's modal state between lines: position, feed, process on/off, the pass being read."""

    pos: dict[str, float] = field(default_factory=lambda: {k: 0.0 for k in "XYZABC"})
    feed: float = 0.0
    on: bool = False
    header: tuple[int, int, str, float, float, float] | None = None
    pts: list[dict[str, float]] = field(default_factory=list)
    feeds: list[float] = field(default_factory=list)
    wfs_now: float | None = None
    wfs: list[float] = field(default_factory=list)
    seen: set[str] = field(default_factory=set)
    speed: float = 0.0
    out: list[ParsedPass] = field(default_factory=list)

    def line(self, raw: str) -> None:
        m = _PASS.fullmatch(raw.strip())
        if m:
            self.header = (int(m[1]), int(m[2]), m[3], float(m[4]), float(m[5]), float(m[6]))
            self.wfs_now, self.wfs = None, []
            return
        if m := _WFS.fullmatch(raw.strip()):
            self.wfs_now = float(m[1])
            return
        code = re.sub(r"\(.*?\)|;.*", "", raw).strip().upper()
        if not code:
            return
        words = dict(_WORD.findall(code.replace(" ", "")))
        if "F" in words:
            self.feed = float(words["F"])
        if any(k in words for k in "XYZABC"):
            self._move(words)
        if words.get("M") in ("3", "4"):   # M3 constant, M4 dynamic power: the process on
            self.on, self.pts, self.feeds, self.speed = True, [dict(self.pos)], [], self.feed
        elif words.get("M") == "5" and self.on:
            self._process_off()

    def _move(self, words: dict[str, str]) -> None:
        self.pos = {k: float(words.get(k, v)) for k, v in self.pos.items()}
        self.seen |= {k for k in "ABC" if k in words}   # axis words are modal: a 5-axis line may leave one out
        if self.on and words.get("G") in ("1", "01"):
            self.pts.append(dict(self.pos))
            self.feeds.append(self.feed)
            if self.wfs_now is not None:
                self.wfs.append(self.wfs_now)
            self.speed = self.feed

    def _process_off(self) -> None:
        self.on = False
        if self.header is None:
            raise InputError("G-code: a process-on block has no (PASS …) header")
        L, i, role, w, cur, wfs = self.header
        rot = sorted(self.seen)
        pts = self.pts
        rotary = np.asarray([[q[k] for k in rot] for q in pts]) if rot else None
        self.out.append(ParsedPass(L, i, role, w, cur, wfs, self.speed, np.asarray([[q["X"], q["Y"], q["Z"]] for q in pts]),
                                   rotary, np.asarray(self.feeds), np.asarray(self.wfs) if self.wfs else None))
        self.header = None

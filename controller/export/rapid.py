"""ABB RAPID: one module with the path as robtargets and ArcWare weld instructions per pass.

- the work object `wobjCell` carries the alignment (part → robot base), so targets stay in the
  part frame and the robot does the transform, as RAPID users expect;
- per pass a `welddata` (travel speed mm/s, wire feed m/min, current A: the process's schedule)
  and `ArcLStart` / `ArcL` / `ArcLEnd` (arc on at the first move, off at the last);
- a pass with per-segment speed or wire feed (cell-job/2) has a `welddata` and a `speeddata` per
  distinct (speed, wire feed) of its segments, and each move names its segment's pair;
- the interpass wait before each layer as `WaitTime`.
Targets carry the tool orientation from the tool axis (controller.export.orient).
"""
from __future__ import annotations

import re

import numpy as np

from controller.export.orient import abb_quaternion, abb_tool_axis, rigid_quaternion
from controller.export.program import Program, ProgramPass, RobotPass
from core.errors import InputError

_EXT = "[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]"


def _n(v: float, nd: int = 3) -> str:
    s = f"{v:.{nd}f}"
    return "0" if float(s) == 0 else s.rstrip("0").rstrip(".")


def _vec(v: np.ndarray, nd: int = 3) -> str:
    return "[" + ",".join(_n(float(x), nd) for x in v) + "]"


def module_name(name: str) -> str:
    """A RAPID identifier (letters, digits, '_', starting with a letter, at most 32 characters)."""
    ident = re.sub(r"[^A-Za-z0-9_]", "_", name)
    if not ident or not ident[0].isalpha():
        ident = "Job_" + ident
    return ident[:32]


def write_rapid(prog: Program, *, travel_mm_min: float, clearance_mm: float) -> list[str]:
    """The program as the lines of one RAPID module (.mod)."""
    mod = module_name(prog.name)
    q = rigid_quaternion(prog.transform)
    out = [f"MODULE {mod}",
           f"  ! cell export of {prog.source}, job sha256 {prog.sha256[:16]}",
           "  ! wobjCell: the alignment measured on the cell (part frame -> robot base)",
           "  PERS tooldata tTorch := [TRUE,[[0,0,0],[1,0,0,0]],[1,[0,0,1],[1,0,0,0],0,0,0]];",
           f"  PERS wobjdata wobjCell := [FALSE,TRUE,\"\",[{_vec(prog.transform[:3, 3])},{_vec(q, 6)}],"
           "[[0,0,0],[1,0,0,0]]];",
           f"  CONST speeddata vTravel := [{_n(travel_mm_min / 60.0)},500,5000,1000];",
           "  PERS seamdata smCell := [0.5,0.5,[0,0,0,0,0,0,0,0,0],0,0,0,0,0,[0,0,0,0,0,0,0,0,0],0,0,"
           "[0,0,0,0,0,0,0,0,0],0,0,0.5];"]
    body: list[str] = []
    last_layer: int | None = None
    for k, p in enumerate(prog.passes):
        wd, move_wd, move_v = _process_data(out, k, p)
        names = []
        for i, (pt, ax) in enumerate(zip(p.points, p.axes)):
            t = f"pP{k}_{i}"
            names.append(t)
            out.append(f"  CONST robtarget {t} := [{_vec(pt)},{_vec(abb_quaternion(ax), 6)},[0,0,0,0],{_EXT}];")
        if p.layer != last_layer:
            body.append(f"    ! LAYER {p.layer}")
            dwell = prog.layer_dwell_s.get(p.layer, 0.0)
            if last_layer is not None and dwell > 0:
                body.append(f"    WaitTime {_n(dwell, 1)};")
            last_layer = p.layer
        body.append(f"    ! PASS L{p.layer} P{p.index} {p.role} W{p.width_mm:.3f}")
        body.append(f"    MoveL Offs({names[0]},0,0,{_n(clearance_mm)}),vTravel,fine,tTorch\\WObj:=wobjCell;")
        body.append(f"    ArcLStart {names[0]},{move_v[0]},smCell,{move_wd[0]},fine,tTorch\\WObj:=wobjCell;")
        for i, t in enumerate(names[1:-1]):
            body.append(f"    ArcL {t},{move_v[i]},smCell,{move_wd[i]},z1,tTorch\\WObj:=wobjCell;")
        body.append(f"    ArcLEnd {names[-1]},{move_v[-1]},smCell,{move_wd[-1]},fine,tTorch\\WObj:=wobjCell;")
        del wd
        body.append(f"    MoveL Offs({names[-1]},0,0,{_n(clearance_mm)}),vTravel,fine,tTorch\\WObj:=wobjCell;")
    out += ["", "  PROC main()", "    ConfL\\Off;"] + body + ["  ENDPROC", "ENDMODULE"]
    return out


def _welddata(name: str, speed_mm_min: float, wfs: float, current_a: float) -> str:
    # welddata: [weld_speed mm/s, org_weld_speed, main_arc [sched, mode, voltage, wirefeed m/min,
    # control, current A, ...], org_arc]
    return (f"  PERS welddata {name} := [{_n(speed_mm_min / 60.0, 4)},0,[1,0,0,{_n(wfs)},0,{_n(current_a, 2)},0,0,0],"
            "[0,0,0,0,0,0,0,0,0]];")


def _process_data(out: list[str], k: int, p: ProgramPass) -> tuple[str, list[str], list[str]]:
    """Declare pass k's weld data; (its welddata, the welddata and speeddata of each move).

    A pass with one speed and wire feed has one welddata `wdPk` and moves at `vTravel` (the
    welddata's weld speed rules while the arc burns). A cell-job/2 pass gets one welddata
    `wdPk_j` and one speeddata `vPk_j` per distinct (speed, wire feed) of its segments, named
    by each move: RAPID speeddata per move."""
    n = len(p.points) - 1
    if p.speeds is None and p.wfs is None:
        wd = f"wdP{k}"
        out.append(_welddata(wd, p.speed_mm_min, p.wfs_m_min, p.current_a))
        return wd, [wd] * max(n, 1), ["vTravel"] * max(n, 1)
    pairs: dict[tuple[str, str], int] = {}
    move_wd, move_v = [], []
    for v, w in zip(p.segment_speeds(), p.segment_wfs()):
        key = (_n(v / 60.0, 4), _n(w))
        if key not in pairs:
            j = pairs[key] = len(pairs)
            out.append(_welddata(f"wdP{k}_{j}", v, w, p.current_a))
            out.append(f"  CONST speeddata vP{k}_{j} := [{key[0]},500,5000,1000];")
        move_wd.append(f"wdP{k}_{pairs[key]}")
        move_v.append(f"vP{k}_{pairs[key]}")
    return move_wd[0], move_wd, move_v


# ---- reading it back --------------------------------------------------------------------------



_NUM = r"-?\d+(?:\.\d+)?(?:E[+-]?\d+)?"
_TARGET = re.compile(rf"CONST robtarget (\w+) := \[\[({_NUM}),({_NUM}),({_NUM})\],\[({_NUM}),({_NUM}),({_NUM}),({_NUM})\]")
_WELD = re.compile(rf"PERS welddata (\w+) := \[({_NUM}),0,\[1,0,0,({_NUM}),0,({_NUM}),")
_PASS = re.compile(r"! PASS L(\d+) P(\d+) (\w+) W([\d.]+)")
_ARC = re.compile(r"(ArcLStart|ArcL|ArcLEnd) (\w+),(\w+),smCell,(\w+),")


def parse_rapid(lines: list[str]) -> list[RobotPass]:
    """The passes of an exported module: targets welded between ArcLStart and ArcLEnd."""
    targets: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    welds: dict[str, tuple[float, float, float]] = {}
    out: list[RobotPass] = []
    head: tuple[int, int, str, float] | None = None
    pts: list[np.ndarray] = []
    axes: list[np.ndarray] = []
    moves: list[tuple[float, float, float]] = []   # the welddata of each move after the start
    for ln in lines:
        if m := _TARGET.search(ln):
            q = np.array([float(m[i]) for i in range(5, 9)])
            targets[m[1]] = (np.array([float(m[2]), float(m[3]), float(m[4])]), abb_tool_axis(q))
        elif m := _WELD.search(ln):
            welds[m[1]] = (float(m[2]) * 60.0, float(m[3]), float(m[4]))
        elif m := _PASS.search(ln):
            head = (int(m[1]), int(m[2]), m[3], float(m[4]))
        elif m := _ARC.search(ln):
            p, a = targets[m[2]]
            if m[1] == "ArcLStart":
                pts, axes, moves = [], [], []
            else:
                moves.append(welds[m[4]])
            pts.append(p)
            axes.append(a)
            if m[1] == "ArcLEnd":
                if head is None:
                    raise InputError("RAPID: an ArcLStart … ArcLEnd block has no '! PASS' header")
                speed, wfs, cur = welds[m[4]]
                mv = np.asarray(moves)
                out.append(RobotPass(*head, speed, wfs, cur, np.asarray(pts), np.asarray(axes), mv[:, 0], mv[:, 1]))
    return out

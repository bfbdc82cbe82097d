"""KUKA KRL: a `.src` / `.dat` pair with `LIN` moves and the weld switched per pass.

- `$BASE` is the alignment (part → robot base) as a FRAME, so the points stay in the part frame;
- the weld is switched by two local subprograms, `WELD_ON(current A, wire feed m/min)` and
  `WELD_OFF()`, over the synergic source's digital and analog outputs (the I/O numbers are the
  cell's; see docs/export.md); the travel speed of each pass is `$VEL.CP` in m/s; a pass with
  per-segment speed or wire feed (cell-job/2) sets `$VEL.CP` (and the wire feed's `$ANOUT[2]`)
  before every move whose value changes;
- the interpass wait before each layer is `WAIT SEC`;
- positions are `E6POS` in the `.dat`, orientation A/B/C from the tool axis.
"""
from __future__ import annotations

import re

import numpy as np
from scipy.spatial.transform import Rotation

from controller.export.orient import kuka_abc, kuka_tool_axis
from controller.export.program import Program, ProgramPass, RobotPass
from core.errors import InputError

CURRENT_FULL_SCALE_A = 500.0   # $ANOUT is -1…1: the source's command range
WFS_FULL_SCALE_M_MIN = 25.0


def _n(v: float, nd: int = 3) -> str:
    s = f"{v:.{nd}f}"
    return "0.0" if float(s) == 0 else s


def program_name(name: str) -> str:
    """A KRL name (letters, digits, '_', at most 24 characters, not starting with a digit)."""
    ident = re.sub(r"[^A-Za-z0-9_]", "_", name)
    if not ident or ident[0].isdigit():
        ident = "JOB_" + ident
    return ident[:24].upper()


def _frame(m: np.ndarray) -> str:
    a, b, c = Rotation.from_matrix(m[:3, :3]).as_euler("ZYX", degrees=True)
    x, y, z = m[:3, 3]
    return f"{{X {_n(x)},Y {_n(y)},Z {_n(z)},A {_n(a, 4)},B {_n(b, 4)},C {_n(c, 4)}}}"


def _e6pos(name: str, pt: np.ndarray, axis: np.ndarray) -> str:
    a, b, c = kuka_abc(axis)
    return (f"DECL E6POS {name}={{X {_n(pt[0])},Y {_n(pt[1])},Z {_n(pt[2])},A {_n(a, 4)},B {_n(b, 4)},"
            f"C {_n(c, 4)},S 6,T 27,E1 0.0,E2 0.0,E3 0.0,E4 0.0,E5 0.0,E6 0.0}}")


def write_krl(prog: Program, *, travel_mm_min: float, clearance_mm: float) -> tuple[list[str], list[str]]:
    """(`.src` lines, `.dat` lines) of the program."""
    name = program_name(prog.name)
    src = ["&ACCESS RVP", "&REL 1", f"DEF {name}( )",
           f"; cell export of {prog.source}, job sha256 {prog.sha256[:16]}",
           "; $BASE: the alignment measured on the cell (part frame -> robot base)",
           "BAS(#INITMOV,0)", f"$BASE = {_frame(prog.transform)}", "$APO.CDIS = 0.5",
           "WELD_OFF( )"]
    dat = ["&ACCESS RVP", "&REL 1", f"DEFDAT {name}"]
    travel = travel_mm_min / 60000.0
    last_layer: int | None = None
    n = 0
    for p in prog.passes:
        if p.layer != last_layer:
            src.append(f"; LAYER {p.layer}")
            dwell = prog.layer_dwell_s.get(p.layer, 0.0)
            if last_layer is not None and dwell > 0:
                src.append(f"WAIT SEC {_n(dwell, 1)}")
            last_layer = p.layer
        src.append(f"; PASS L{p.layer} P{p.index} {p.role} W{p.width_mm:.3f}")
        lift = np.array([0.0, 0.0, clearance_mm])
        names = []
        for pt, ax in zip(p.points, p.axes):
            n += 1
            names.append(f"XP{n}")
            dat.append(_e6pos(names[-1], pt, ax))
        dat += [_e6pos(f"XA{n}", p.points[0] + lift, p.axes[0]), _e6pos(f"XR{n}", p.points[-1] + lift, p.axes[-1])]
        wfs0 = float(p.segment_wfs()[0])
        src += [f"$VEL.CP = {_n(travel, 5)}", f"LIN XA{n}", f"LIN {names[0]}",
                f"WELD_ON({_n(p.current_a, 2)}, {_n(wfs0)})"]
        src += _weld_moves(p, names)
        src += ["WELD_OFF( )", f"$VEL.CP = {_n(travel, 5)}", f"LIN XR{n}"]
    src += ["END", "",
            "DEF WELD_ON(CURRENT_A:IN, WFS_M_MIN:IN)",
            "REAL CURRENT_A, WFS_M_MIN",
            f"$ANOUT[1] = CURRENT_A / {_n(CURRENT_FULL_SCALE_A, 1)}",
            f"$ANOUT[2] = WFS_M_MIN / {_n(WFS_FULL_SCALE_M_MIN, 1)}",
            "$OUT[1] = TRUE", "WAIT FOR $IN[1]", "END", "",
            "DEF WELD_OFF( )", "$OUT[1] = FALSE", "WAIT FOR NOT $IN[1]", "END"]
    dat += ["ENDDAT"]
    return src, dat


def _weld_moves(p: ProgramPass, names: list[str]) -> list[str]:
    """The LINs of a pass with the arc on: `$VEL.CP` before the first and before every move whose
    speed changes, the wire feed's analog output before every move whose wire feed changes."""
    out: list[str] = []
    vel = wfs = ""
    for i, (t, v, w) in enumerate(zip(names[1:], p.segment_speeds(), p.segment_wfs())):
        vv, ww = _n(v / 60000.0, 8), _n(float(w))
        if ww != wfs and i > 0:
            out.append(f"$ANOUT[2] = {ww} / {_n(WFS_FULL_SCALE_M_MIN, 1)}")
        if vv != vel:
            out.append(f"$VEL.CP = {vv}")
        out.append(f"LIN {t}" + (" C_DIS" if i < len(names) - 2 else ""))
        vel, wfs = vv, ww
    return out


# ---- reading it back --------------------------------------------------------------------------



_NUM = r"-?\d+(?:\.\d+)?"
_POS = re.compile(rf"DECL E6POS (X[PAR]\d+)=\{{X ({_NUM}),Y ({_NUM}),Z ({_NUM}),A ({_NUM}),B ({_NUM}),C ({_NUM})")
_PASS = re.compile(r"; PASS L(\d+) P(\d+) (\w+) W([\d.]+)")
_ON = re.compile(rf"WELD_ON\(({_NUM}), ({_NUM})\)")
_VEL = re.compile(rf"\$VEL\.CP = ({_NUM})")
_LIN = re.compile(r"LIN (X[PAR]\d+)(?: C_DIS)?$")
_WFS = re.compile(rf"\$ANOUT\[2\] = ({_NUM}) / ")


def parse_krl(src: list[str], dat: list[str]) -> list[RobotPass]:
    """The passes of an exported pair: the LIN targets between WELD_ON and WELD_OFF."""
    pos: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for ln in dat:
        if m := _POS.search(ln):
            v = [float(m[i]) for i in range(2, 8)]
            pos[m[1]] = (np.array(v[:3]), kuka_tool_axis(np.array(v[3:])))
    out: list[RobotPass] = []
    head: tuple[int, int, str, float] | None = None
    weld: tuple[float, float] | None = None
    vel = 0.0
    last: str | None = None
    pts: list[np.ndarray | None] = []  # [None] while WELD_ON has no LIN target before it
    axes: list[np.ndarray | None] = []
    moves: list[tuple[float, float]] = []   # (speed, wire feed) of each weld move
    wfs = 0.0
    for ln in (s.strip() for s in src):
        if m := _PASS.match(ln):
            head = (int(m[1]), int(m[2]), m[3], float(m[4]))
        elif m := _ON.match(ln):
            weld = (float(m[1]), float(m[2]))
            p, a = pos[last] if last else (None, None)
            pts, axes, moves, wfs = [p], [a], [], weld[1]
        elif m := _WFS.match(ln):
            wfs = float(m[1])
        elif m := _VEL.match(ln):
            vel = float(m[1]) * 60000.0
        elif m := _LIN.match(ln):
            last = m[1]
            if weld is not None:
                pts.append(pos[last][0])
                axes.append(pos[last][1])
                moves.append((vel, wfs))
        elif ln.startswith("WELD_OFF") and weld is not None:
            if head is None or pts[0] is None:
                raise InputError("KRL: a WELD_ON … WELD_OFF block has no '; PASS' header or start")
            mv = np.asarray(moves)
            out.append(RobotPass(*head, vel, weld[1], weld[0], np.asarray(pts), np.asarray(axes), mv[:, 0], mv[:, 1]))
            weld = None
    return out

"""Milling programs on the grbl CNC: a finish plan as G-code, the tool change, `$32=0` (docs/machining.md).

- `program_lines(plan, transform, cutter)`: the plan's passes (CAD frame) moved to the machine by
  the alignment transform, each pass `G0` over its start, `G1` down at the plunge feed, `G1` along
  it at the cutter's feed (collinear points merged), `G0` up; the spindle `M3 S<rpm>` with a
  dwell for it to come up to speed, `M5` at the end.
- `change_tool(link, tools, number)`: grblHAL takes `T<n> M6` (it waits in state Tool for the
  cycle start) and the length from cell.yaml (`G43.1 Z<offset>`); stock grbl 1.1h has no M6: a programmed pause `T<n> M0` with a message for
  the operator, cycle start, then the cutter's length measured on the tool setter (`G38.2` down
  onto `tools.setter_mm`) and applied as `G43.1 Z<measured>`. The deposition head with its touch
  probe is the length reference (`G49`).
- `run_program(link, lines)`: `$32=0` set and read back, the program streamed, every line `ok`,
  under the progress watch (controller/motion/watch.py): a machine that stands, in Run or not, for
  the program's bound (twice its longest dwell + 1 s of process time: between dwells a machining
  program moves all the time) is a StallFault after the safe stop (feed hold, then `M5` or a soft
  reset, the spindle verified off); at the end the status report must show the spindle off
  (`FS:` speed 0, no `S`/`C` in `A:`) before the next step (a probe touch) may start.
"""
from __future__ import annotations

import asyncio
import re
import time

import numpy as np
from numpy.typing import NDArray

from controller.motion.watch import MotionWatch, Sample
from controller.ports import CncLinkPort
from core.errors import CellError
from core.tools import Cutter, Tools
from wire.grbl_protocol import GrblStatus
from planner.finish import FinishPlan

F = NDArray[np.float64]
SPINDLE_UP_S = 2.0       # dwell after M3 for the spindle to reach its speed
SETTER_FEED_MM_MIN = 100.0


def _f(v: float) -> str:
    return f"{v:.3f}"


def _merge_collinear(p: F, tol: float = 1e-6) -> F:
    """Drop the points that lie on the straight line between their neighbours."""
    if len(p) <= 2:
        return p
    keep = [0]
    for i in range(1, len(p) - 1):
        a, b, c = p[keep[-1]], p[i], p[i + 1]
        ab, ac = b - a, c - a
        n = float(np.linalg.norm(ac))
        off = float(np.linalg.norm(np.cross(ab, ac))) / n if n > 1e-12 else float(np.linalg.norm(ab))
        if off > tol or float(np.dot(ab, ac)) < 0:
            keep.append(i)
    keep.append(len(p) - 1)
    return p[keep]


def to_machine(points: F, transform: F) -> F:
    tf = np.asarray(transform, dtype=float)
    out: F = np.asarray(points, dtype=float) @ tf[:3, :3].T + tf[:3, 3]
    return out


def program_lines(plan: FinishPlan, transform: F, cutter: Cutter, *, comment: bool = True,
                  spindle_up_s: float = SPINDLE_UP_S) -> list[str]:
    """The plan's passes as grbl G-code in the machine frame (tool loaded, its length applied)."""
    tf = np.asarray(transform, dtype=float)
    safe = float((tf @ np.array([0.0, 0.0, plan.safe_z_mm, 1.0]))[2])
    out = [f"(cell finish: {plan.tool}, {len(plan.passes)} passes)"] if comment else []
    out += ["G90 G21 G94", f"M3 S{cutter.spindle_rpm:.0f}", f"G4 P{spindle_up_s:g}", f"G0 Z{_f(safe)}"]
    plunge = min(cutter.feed_mm_min, 300.0)
    for p in plan.passes:
        q = _merge_collinear(to_machine(p.points, tf))
        out += [f"G0 X{_f(q[0, 0])} Y{_f(q[0, 1])}", f"G1 Z{_f(q[0, 2])} F{plunge:.0f}"]
        out += [f"G1 X{_f(x)} Y{_f(y)} Z{_f(z)}" + (f" F{cutter.feed_mm_min:.0f}" if k == 0 else "")
                for k, (x, y, z) in enumerate(q[1:])]
        out.append(f"G0 Z{_f(safe)}")
    out.append("M5")
    return out


def tool_change_lines(firmware: str, number: int, name: str, length_mm: float) -> list[str]:
    """The change as a program carries it (exports): grblHAL `T M6` + `G43.1`; grbl 1.1h a pause."""
    if "hal" in firmware.lower():
        return ["G49", f"T{number} M6", f"G43.1 Z{_f(length_mm)}"]
    return ["G49", f"(MSG,load T{number} {name} then cycle start)", f"T{number} M0",
            f"G43.1 Z{_f(length_mm)}"]


async def _wait_hold(link: CncLinkPort, timeout_s: float = 30.0) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        st = await link.status()
        if st.state.startswith(("Hold", "Tool")):   # grbl's pause; grblHAL's manual tool change
            return
        if st.state.startswith("Alarm"):
            raise CellError(f"cnc at {link.url}: alarm during the tool change pause")
        await asyncio.sleep(0.02)
    raise CellError(f"cnc at {link.url}: the tool change pause (M0) was not reached in {timeout_s:g} s")


async def pause(link: CncLinkPort, line: str) -> None:
    """Send a line that pauses (grbl's `M0`, grblHAL's `M6`) and take it through the pause: grbl
    answers `M0`'s `ok` only after the cycle start, so the line waits in a task while the pause
    (state Hold or Tool) is awaited and `~` sent."""
    sent = asyncio.ensure_future(link.command(line, timeout=60.0))
    try:
        await _wait_hold(link)
        await link.resume()
        await sent
    finally:
        if not sent.done():
            sent.cancel()
    await link.wait_idle(30.0)


async def measure_length(link: CncLinkPort, tools: Tools, clear_z: float) -> float:
    """The loaded tool's length on the tool setter: `G38.2` down onto its top (no offset active)."""
    sx, sy, sz = tools.setter_mm
    reach = max([abs(c.length_offset_mm) for c in tools.cutters.values()] + [0.0]) + 20.0
    await link.stream([f"G0 Z{_f(clear_z)}", f"G0 X{_f(sx)} Y{_f(sy)}", f"G0 Z{_f(sz + reach)}"])
    got = await link.probe((sx, sy, sz - 5.0), SETTER_FEED_MM_MIN)
    if not got.contact:
        raise CellError(f"cnc at {link.url}: no contact on the tool setter at {sx:g}, {sy:g}, {sz:g}")
    await link.stream([f"G0 Z{_f(clear_z)}"])
    return float(got.position[2]) - sz


async def change_tool(link: CncLinkPort, tools: Tools, number: int, clear_z: float) -> float:
    """Load tool `number` (the head or a cutter) and apply its length; returns the length used."""
    name, length = "deposition head", tools.deposition.length_offset_mm
    for n, c in tools.cutters.items():
        if c.number == number:
            name, length = n, c.length_offset_mm
    await link.stream(["M5", "G49", f"G0 Z{_f(clear_z)}"])
    if "hal" in link.firmware.lower():   # grblHAL: `M6` waits in state Tool for the cycle start
        await pause(link, f"T{number} M6")
        await link.command(f"G43.1 Z{_f(length)}")
        return length
    # grbl 1.1h: a programmed pause; the operator loads the tool and presses cycle start
    # (unattended: the controller sends it once the pause is reached, docs/machining.md)
    await link.command(f"(MSG,load T{number} {name} then cycle start)")
    await pause(link, f"T{number} M0")
    if number != tools.deposition.number:
        length = await measure_length(link, tools, clear_z)
    await link.command(f"G43.1 Z{_f(length)}")
    return length


def program_bound_s(lines: list[str]) -> float:
    """The progress bound of a milling program (process s): twice its longest dwell + 1 s."""
    dwells = [float(m.group(1)) for line in lines for m in [re.search(r"\bG4\s*P([0-9.]+)", line)] if m]
    return 2.0 * max(dwells, default=0.0) + 1.0


def machining_watch(link: CncLinkPort, lines: list[str]) -> MotionWatch:
    """The watch of a milling program on `link` (its bound from `program_bound_s`)."""
    async def read() -> Sample:
        st = await link.status()
        return Sample(time.monotonic(), tuple(float(v) for v in st.mpos), None, st.state)

    async def stop(_s: Sample) -> str:
        res = await link.safe_stop("machining made no progress")
        return f"motion held, spindle and laser off ({res.summary()})"

    return MotionWatch(device="cnc", state="machining", read=read, stop=stop, bound_process_s=program_bound_s(lines),
                       time_scale=float(link.line_scale), status_period_s=float(link.status_period))


async def run_program(link: CncLinkPort, lines: list[str]) -> float:
    """`$32=0` (read back), then the program streamed under the progress watch, every line `ok`,
    the spindle off in the status report at its end; returns its wall seconds."""
    await link.laser_mode(False)
    t0 = time.monotonic()

    async def body() -> GrblStatus:
        await link.stream(lines)
        return await link.wait_idle(600.0)

    st = await machining_watch(link, lines).guard(body())
    if st.state.startswith("Alarm"):
        raise CellError(f"cnc at {link.url}: alarm while machining; see the controller's messages")
    st = await link.status()
    if st.spindle > 0 or st.spindle_on:
        res = await link.safe_stop("the spindle still turned after the milling program")
        raise CellError(f"cnc at {link.url}: the spindle still turns after the milling program's M5 (status "
                        f"{st.state}, spindle {st.spindle:g} rpm, accessories {st.accessories!r}); stopped: "
                        f"{res.summary()}")
    return time.monotonic() - t0

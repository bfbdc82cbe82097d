"""The CNC's homing and probing under the progress watch (docs/contract.md §6; controller/motion/watch.py).

Probing: every probe step (the rapids grbl finishes before a `G38.x`, and the probing move) is
watched from the status reports; a machine that stands, in Run or not, for the step's bound is a
fault naming the device, the state and how long it stood, after the safe stop (feed hold, then
`M5` or a soft reset, verified). The bound: the probing move's travel at its feed × 2 + 1 s.

Homing: grbl answers nothing (not even `?`) while it homes, so progress cannot be sampled; the
bound is the homing cycle the machine's own settings plan (`$H` seeks over the longest axis travel
`$130`-`$132` at the seek rate `$25`, locates at the feed `$24` and pulls off `$27`), × 2 + 1 s,
and a cycle that has not finished by then is the same fault, after a soft reset.
"""
from __future__ import annotations

import re
import time
from typing import Awaitable, TypeVar

from controller.motion.watch import MotionWatch, Sample, StallFault, move_bound_s, wall_bound_s
from controller.ports import ProbePort
from drivers.errors import DeviceTimeout
from wire.grbl_protocol import GrblStatus

T = TypeVar("T")
_SETTING = re.compile(r"^\$(\d+)=([-+0-9.]+)")


def _settings(lines: list[str]) -> dict[int, float]:
    out: dict[int, float] = {}
    for text in lines:
        m = _SETTING.match(text.strip())
        if m is not None:
            out[int(m.group(1))] = float(m.group(2))
    return out


def homing_bound_s(settings: dict[int, float]) -> float:
    """The homing cycle's bound in process seconds from grbl's settings: seek the longest travel,
    locate and pull off twice, × 2 + 1 s."""
    travel = max((settings.get(n, 0.0) for n in (130, 131, 132)), default=0.0) or 1000.0
    seek = settings.get(25, 500.0) or 500.0
    feed = settings.get(24, 25.0) or 25.0
    pull = settings.get(27, 1.0)
    cycle = travel / (seek / 60.0) + 2 * pull / (feed / 60.0) + 2 * pull / (seek / 60.0)
    return 2.0 * cycle + 1.0


async def home(link: ProbePort) -> GrblStatus:
    """`$H` with the bound of its plan; a cycle that does not finish within it is a StallFault
    (after a soft reset: the safe stop)."""
    bound = homing_bound_s(_settings(await link.command("$$")))
    scale = max(float(link.line_scale), 1e-9)
    wall = wall_bound_s(bound, scale)
    t0 = time.monotonic()
    try:
        return await link.home(timeout=wall)
    except DeviceTimeout:
        stood = time.monotonic() - t0
        stop = await link.safe_stop("homing made no progress")
        proc = f" ({stood * scale:.1f} s of process time)" if abs(scale - 1.0) > 1e-9 else ""
        raise StallFault(f"cnc made no progress for {stood:.2f} s{proc} in homing ($H unanswered; progress "
                         f"timeout {bound:.2f} s of process time from $130-$132, $24, $25, $27, {wall:.2f} s "
                         f"wall): motion held, spindle and laser off ({stop.summary()}); check the limit "
                         "switches, then home again") from None


def probing_watch(link: ProbePort, where: str, travel_mm: float, feed_mm_min: float) -> MotionWatch:
    """The watch of one probe step toward `where` (its travel at its feed × 2 + 1 s)."""
    async def read() -> Sample:
        st = await link.status()
        return Sample(time.monotonic(), tuple(float(v) for v in st.mpos), None, st.state)

    async def stop(_s: Sample) -> str:
        res = await link.safe_stop(f"probing made no progress at {where}")
        return f"motion held, spindle and laser off ({res.summary()})"

    return MotionWatch(device="cnc", state="probing", read=read, stop=stop,
                       bound_process_s=move_bound_s(travel_mm, feed_mm_min), time_scale=float(link.line_scale),
                       status_period_s=float(link.status_period), where=lambda: where)


async def probing(link: ProbePort, step: Awaitable[T], where: str, travel_mm: float, feed_mm_min: float) -> T:
    """Await a probe step under its watch (StallFault on a stall, the machine safely stopped)."""
    return await probing_watch(link, where, travel_mm, feed_mm_min).guard(step)

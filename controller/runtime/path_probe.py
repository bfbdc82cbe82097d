"""The path loop's touches along every pass on the CNC (docs/closed-loop.md "The CNC with probing").

A point, three lines sent together: `G0 Z` to the hop height (`hop_mm` above the highest of the
spot's planned top, the top just touched next to it and the top the layer probed before left there
raised by the commanded rise), `G0 X Y` over the point, `G38.2 Z` down at
the touch feed to `depth_mm` below the lower of the two; grbl's latched trip (`[PRB:…]`) is the top.
grbl answers a `G0` once it is planned and holds the `G38.2` until the motion before it is done, so
the three lines need not wait for each other's replies. The points are visited from the end of the
list nearer the head (a layer ends at one end of the part: its first point at the other end cost a
travel over the part).

The alignment's and the repair's cycle (controller/align/probe_cycle.py: from the safe height, a
fast touch, a back-off, slow touches and a spread check) is not used here: nine lines and two
touches a point, each waiting for its reply.

The process is off (checked from a status report before the first touch: the newest background
report when it came in after the last reply, else a fresh one); an unhomed link is homed
first. A touch that finds nothing within its travel (ALARM:5) or starts tripped (ALARM:4) is a
ProbeCycleError naming the point, after the driver's recovery (unlock, retract).
"""
from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from typing import Sequence

from controller.align.probe_cycle import ProbeCycleError
from controller.align.watched import home, probing
from controller.ports import CncLinkPort, ProbePort
from core.errors import CellError
from drivers.grbl import ProbeError
from wire.grbl_protocol import GrblStatus, fmt

__all__ = ["TouchPlan", "expected_tops", "touch_tops"]

Spot = tuple[float, float, float]


@dataclass(frozen=True)
class TouchPlan:
    """Heights relative to a spot's expected top (mm) and the touch feed (mm/min)."""

    hop_mm: float = 1.5            # travel height between points
    depth_mm: float = 18.0         # the touch reaches this far below
    touch_feed: float = 1800.0     # G38.2


async def _point(link: ProbePort, where: str, x: float, y: float, up: float, low: float, feed: float) -> float:
    """Up, over, down: the three lines sent at once; the trip z."""
    moves = [asyncio.ensure_future(link.command(f"G90 G0 Z{fmt(up)}")),
             asyncio.ensure_future(link.command(f"G0 X{fmt(x)} Y{fmt(y)}"))]
    failed: BaseException | None = None
    try:
        res = await probing(link, link.probe((x, y, low), feed, mode="G38.2"), f"probe point {where}", up - low, feed)
    except ProbeError as exc:
        failed = ProbeCycleError(f"probe point {where}: no top found from {up:.3f} down to {low:.3f} (machine z) "
                                 f"({exc}); check the part and the probe")
    finally:
        done = await asyncio.gather(*moves, return_exceptions=True)
    for d in done:     # a rapid refused (its error) comes before the touch's own
        if isinstance(d, BaseException):
            raise d
    if failed is not None:
        raise failed
    if not res.contact:
        raise ProbeCycleError(f"probe point {where}: no contact from {up:.3f} down to {low:.3f} (machine z)")
    return float(res.position[2])


def _after_last_reply(link: CncLinkPort) -> GrblStatus | None:
    """The newest background report when it came in after the last reply (the stream's closing
    `G4 P0`, answered once its `M5` had run): it shows the machine as it is now. grbl prints a
    report when it reads the `?`, in order with its replies, so a report after the reply was made
    after it."""
    st = link.latest_status
    return st if st is not None and link.status_t > link.answer_t else None


def expected_tops(before: Sequence[Spot], tops: Sequence[float], spots: Sequence[Spot]) -> list[float]:
    """Where each spot's top should stand: the top touched at the nearest spot of the layer probed
    before, raised by the commanded rise since (the spots' z difference)."""
    if not before:
        return [z for _, _, z in spots]
    out = []
    for x, y, z in spots:
        j = min(range(len(before)), key=lambda i: math.dist((x, y), before[i][:2]))
        out.append(tops[j] + (z - before[j][2]))
    return out


async def touch_tops(link: CncLinkPort, spots: Sequence[Spot], plan: TouchPlan, name: str = "layer",
                     expect: Sequence[float] | None = None) -> list[float]:
    """The machine z of the deposit's top under each spot (x, y, planned top), one touch each, in
    the spots' order. `expect`: where each top should stand (expected_tops), when known: the
    travel clears it too."""
    st = _after_last_reply(link) or await link.status(at_once=True)
    if st.spindle:
        raise CellError(f"{name}: the process is still on (spindle {st.spindle}); no probing with the process on")
    if not link.homed:
        st = await home(link)
    if not spots:
        return []
    head = (float(st.mpos[0]), float(st.mpos[1]))
    order = list(range(len(spots)))
    if math.dist(head, spots[-1][:2]) < math.dist(head, spots[0][:2]):
        order.reverse()
    z_now = float(st.mpos[2])
    tops: dict[int, float] = {}
    for n, k in enumerate(order):
        x, y, z = spots[k]
        high = max(z, expect[k]) if expect is not None else z
        near = z_now if n else z        # the neighbour just touched, else the plan
        up = max(high, near) + plan.hop_mm if n else max(high + plan.hop_mm, z_now)
        z_now = await _point(link, f"{name}[{k}] at x {x:.2f}, y {y:.2f}", x, y, up,
                             min(z, near) - plan.depth_mm, plan.touch_feed)
        tops[k] = z_now
    await link.command(f"G0 Z{fmt(max(z_now, spots[order[-1]][2]) + plan.hop_mm)}")
    return [tops[k] for k in range(len(spots))]

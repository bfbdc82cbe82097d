"""The top of a just-deposited layer, probed between layers on the CNC (docs/closed-loop.md).

A few points on the layer's beads (their centre lines, spread over the layer's deposit length,
away from each bead's start and end where the pool starts and craters), each touched with the
existing probe cycle (controller/align/probe_cycle.py: G38.2 fast, back off, slow samples) from
`clearance` above the layer's commanded z, straight down. The process is off (the stream ended
with `M5`; checked from the status report before the first touch). Machine coordinates: a 3-axis
job's points are machine positions (the cycle reads the trip positions).
"""
from __future__ import annotations

import math
from typing import Sequence

from controller.align.watched import home
from controller.align.probe_cycle import ProbeLog, ProbeTarget, probe_point
from controller.ports import ProbePort
from core.config import ProbeSettings
from core.errors import CellError
from planner.job import Pass

__all__ = ["probe_spots", "probe_layer_top"]

Point = tuple[float, float, float]


def _segments(points: Sequence[Sequence[float]]) -> list[tuple[Point, Point, float]]:
    out = []
    for a, b in zip(points, points[1:]):
        pa = (float(a[0]), float(a[1]), float(a[2]))
        pb = (float(b[0]), float(b[1]), float(b[2]))
        out.append((pa, pb, math.dist(pa[:2], pb[:2])))
    return out


def _at(segs: list[tuple[Point, Point, float]], s: float) -> Point:
    for a, b, length in segs:
        if s <= length or (a, b, length) == segs[-1]:
            t = 0.0 if length <= 0 else min(max(s / length, 0.0), 1.0)
            return (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2]))
        s -= length
    return segs[-1][1]


def probe_spots(passes: Sequence[Pass], n: int, middle: float = 0.6) -> list[Point]:
    """`n` points on the passes' centre lines, evenly over the middle share of each pass."""
    spans = []
    for p in passes:
        segs = _segments(p.points.tolist())
        total = sum(s[2] for s in segs)
        if total > 0:
            spans.append((segs, total))
    if not spans or n <= 0:
        return []
    usable = sum(t * middle for _, t in spans)
    out = []
    for k in range(n):
        s = (k + 0.5) / n * usable
        for segs, total in spans:
            if s <= total * middle or (segs, total) == spans[-1]:
                out.append(_at(segs, total * (1.0 - middle) / 2.0 + min(s, total * middle)))
                break
            s -= total * middle
    return out


async def probe_layer_top(link: ProbePort, settings: ProbeSettings, spots: Sequence[Point], clearance_mm: float,
                          name: str = "layer", log: ProbeLog | None = None) -> list[float]:
    """The z of the deposit's top under each spot (machine z), by the probe cycle."""
    st = await link.status()
    if st.spindle:
        raise CellError(f"{name}: the process is still on (spindle {st.spindle}); no probing with the process on")
    if not link.homed:
        await home(link)   # the homing cycle's bound from the machine's settings
    tops = []
    for k, (x, y, z) in enumerate(spots):
        start = (x, y, z + clearance_mm)
        t = ProbeTarget(name=f"{name}[{k}]", start=start, direction=(0.0, 0.0, -1.0), safe_z=z + clearance_mm)
        pt = await probe_point(link, t, settings, log)
        tops.append(float(pt.position[2]))
    return tops

"""The CNC simulator's executor step: the head planner block moved over a stretch of simulated
time, at its feed or decelerating to a stop in a feed hold (`CncSim.advance` calls it).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

from sims.cnc_block import DEVICE, Block, Pos5, pos5

if TYPE_CHECKING:
    from sims.cnc_sim import CncSim

def move_block(sim: CncSim, b: Block, target: Pos5, t: float, now: float) -> float | None:
    """Move the head block toward `target` from t to at most now: the time it ended, or None
    when it is still under way at `now` (or decelerating in a feed hold)."""
    if not b.started:
        b.started = True
        if b.probe:
            start_probe(sim, b)
            # the move ends where the stylus touches: when the whole probing move fits in this
            # tick it must not run on to the commanded end (it went through the part, 1 run in 3)
            target = b.target if b.target is not None else target
    if sim.spindle_on:
        sim.spindle_s = b.s  # laser mode: S changes apply in motion
    p0 = pos5(sim.pos)
    delta = [e - s for s, e in zip(p0, target)]
    dist = math.sqrt(sum(d * d for d in delta))
    v = max(b.feed, 1e-6) / 60.0
    if sim.hold:  # decelerating to a stop (Hold:1): speed falls linearly to 0
        _decelerate(sim, b, target, p0, delta, dist, t, now)
        return None
    need = dist / v
    if t + need <= now:
        sim._moved(b, p0, target, t, t + need)
        t += need
        if b.probe:
            sim._latch = tuple(sim.pos) if b.contact else None
        sim._finish(b, t)
        return t
    f = (now - t) * v / dist
    sim._moved(b, p0, pos5([a + f * d for a, d in zip(p0, delta)]), t, now)
    return None


def _decelerate(sim: CncSim, b: Block, target: Pos5, p0: Pos5, delta: list[float], dist: float,
                t: float, now: float) -> None:
    """The head block's travel in [t, now] while a feed hold brings it to a stop."""
    th, dec = sim._hold_t or t, max(sim._hold_decel, 1e-9)
    a0, a1 = max(t - th, 0.0), min(now - th, dec)
    travel = sim._hold_v * ((a1 - a0) - (a1 * a1 - a0 * a0) / (2 * dec)) if a1 > a0 else 0.0
    stop = now - th >= dec
    if travel >= dist:
        p1, t1 = target, now
    else:
        f = travel / dist if dist > 0 else 0.0
        p1, t1 = pos5([a + f * d for a, d in zip(p0, delta)]), now
    sim._moved(b, p0, p1, t, t1)
    if travel >= dist:
        sim._finish(b, t1)
    if stop:
        sim.hold_sub = 0
        if sim.world is not None:
            sim.world.motion_stopped(DEVICE)
        sim._notify()


def start_probe(sim: CncSim, b: Block) -> None:
    """At the start of a probing move: cut it short where the stylus will touch the part."""
    if b.target is None:
        return
    f = sim.spindle.setter_hit(pos5(sim.pos), b.target)
    if f is not None:   # the tool setter (any tool): its switch is on the probe input
        b.target = pos5([a + f * (e - a) for a, e in zip(sim.pos, b.target)])
        b.contact = True
        return
    if sim.workpiece is None or sim.spindle.is_cutter:
        return
    hit = sim.workpiece.probe(sim.pos[:3], b.target[:3], sim.pos[3], sim.pos[4])
    if hit is not None:
        b.target = (hit[0], hit[1], hit[2], sim.pos[3], sim.pos[4])
        b.contact = True

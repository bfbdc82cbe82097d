"""The CNC simulator's executor step: the head planner block moved over a stretch of simulated
time, at its feed or decelerating to a stop in a feed hold (`CncSim.advance` calls it), and what
follows a stretch of motion (`moved`) and a finished block (`finish`). Works on the shared
`CncState` (state.py) and the simulator's public parts (`CncParts`).
"""
from __future__ import annotations

import math

from sims.cnc.block import DEVICE, Block, Pos5, pos5
from sims.cnc.cut import Breakage
from sims.cnc.state import CncParts


def move_block(sim: CncParts, b: Block, target: Pos5, t: float, now: float) -> float | None:
    """Move the head block toward `target` from t to at most now: the time it ended, or None
    when it is still under way at `now` (or decelerating in a feed hold)."""
    if not b.started:
        b.started = True
        if b.probe:
            start_probe(sim, b)
            # the move ends where the stylus touches: when the whole probing move fits in this
            # tick it must not run on to the commanded end (it went through the part, 1 run in 3)
            target = b.target if b.target is not None else target
    if sim.machine.spindle_on:
        sim.machine.spindle_s = b.s  # laser mode: S changes apply in motion
    p0 = pos5(sim.machine.pos)
    delta = [e - s for s, e in zip(p0, target)]
    dist = math.sqrt(sum(d * d for d in delta))
    v = max(b.feed, 1e-6) / 60.0
    sim.machine.speed_mm_min = b.feed
    if sim.machine.hold:  # decelerating to a stop (Hold:1): speed falls linearly to 0
        _decelerate(sim, b, target, p0, delta, dist, t, now)
        return None
    need = dist / v
    if t + need <= now:
        moved(sim, b, p0, target, t, t + need)
        t += need
        if b.probe:
            sim.machine.latch = tuple(sim.machine.pos) if b.contact else None
        finish(sim, b, t)
        return t
    f = (now - t) * v / dist
    moved(sim, b, p0, pos5([a + f * d for a, d in zip(p0, delta)]), t, now)
    return None


def _decelerate(sim: CncParts, b: Block, target: Pos5, p0: Pos5, delta: list[float], dist: float,
                t: float, now: float) -> None:
    """The head block's travel in [t, now] while a feed hold brings it to a stop."""
    th, dec = sim.machine.hold_t or t, max(sim.machine.hold_decel, 1e-9)
    a0, a1 = max(t - th, 0.0), min(now - th, dec)
    travel = sim.machine.hold_v * ((a1 - a0) - (a1 * a1 - a0 * a0) / (2 * dec)) if a1 > a0 else 0.0
    sim.machine.speed_mm_min = sim.machine.hold_v * 60.0 * max(1.0 - a1 / dec, 0.0)   # the speed at `now`
    stop = now - th >= dec
    if travel >= dist:
        p1, t1 = target, now
    else:
        f = travel / dist if dist > 0 else 0.0
        p1, t1 = pos5([a + f * d for a, d in zip(p0, delta)]), now
    moved(sim, b, p0, p1, t, t1)
    if travel >= dist:
        finish(sim, b, t1)
    if stop:
        sim.machine.hold_sub = 0
        if sim.world is not None:
            sim.world.motion_stopped(DEVICE)
        sim.machine.notify()


def start_probe(sim: CncParts, b: Block) -> None:
    """At the start of a probing move: cut it short where the stylus will touch the part."""
    if b.target is None:
        return
    f = sim.spindle.setter_hit(pos5(sim.machine.pos), b.target)
    if f is not None:   # the tool setter (any tool): its switch is on the probe input
        b.target = pos5([a + f * (e - a) for a, e in zip(sim.machine.pos, b.target)])
        b.contact = True
        return
    if sim.workpiece is None or sim.spindle.is_cutter:
        return
    hit = sim.workpiece.probe(sim.machine.pos[:3], b.target[:3], sim.machine.pos[3], sim.machine.pos[4])
    if hit is not None:
        b.target = (hit[0], hit[1], hit[2], sim.machine.pos[3], sim.machine.pos[4])
        b.contact = True


def finish(sim: CncParts, b: Block, t: float) -> None:
    """Block `b` has executed at `t`: off the planner, into the log, the World told."""
    if not sim.machine.queue or sim.machine.queue[0] is not b:   # flushed by an alarm while it moved
        b.done = True
        return
    sim.machine.queue.popleft()
    sim.spindle.finished(b, t)
    b.done = True
    if b.motion:
        sim.machine.motion_in_queue -= 1
        if sim.world is not None:
            sim.world.motion_stopped(DEVICE)
    sim.log_block(b, t)
    if not any(x.motion for x in sim.machine.queue) and sim.rx_fill:
        sim.starved += 1
    sim.machine.notify()


def moved(sim: CncParts, b: Block, p0: Pos5, p1: Pos5, t0: float, t1: float) -> None:
    """The head block went from p0 to p1 over [t0, t1]: the spindle cuts, the World sees the torch."""
    sim.machine.pos = list(p1)
    try:   # laser mode ($32=1) stops the spindle on rapids
        sim.spindle.moved(b, p0, p1, sim.machine.spindle_on and sim.machine.spindle_s > 0
                          and not (int(sim.machine.settings[32]) and b.verb == "G0"), sim.machine.spindle_s)
    except Breakage as exc:
        sim.send(f"[MSG:Tool breakage: {exc}]")
        sim.machine.queue.clear()
        sim.machine.motion_in_queue = 0
        sim.machine.spindle_on = False
        sim.machine.homed = False
        sim.raise_alarm(1)
        sim.machine.notify()
    if sim.world is not None and p0 != p1:
        part = None
        if sim.workpiece is not None:  # the segment on the part, from the sim's own true pose
            q0, _ = sim.workpiece.part_frame(p0)
            q1, ax = sim.workpiece.part_frame(p1)
            part = (tuple(q0), tuple(q1), tuple(ax))
        sim.world.torch_moved(DEVICE, b.seq, p0[:3], p1[:3], t0, t1, part=part)

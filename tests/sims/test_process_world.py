"""The simulated world's shape (issue 27): height map, CTWD, probe on the grown part, current vs stick-out."""
from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from controller.defaults import SIM_REPLY_TIMEOUT_MS

from controller.runtime.arc_handshake import ArcHandshake
from core.config import ProcessSim, load_material
from core.melting import synergic_current
from drivers.power_modbus import ModbusPowerSource
from planner.process import inverse
from sims.clock import SimClock
from sims.heightmap import HeightMap
from sims.power_sim import PowerSourceSim, serve_modbus_tcp
from sims.process_world import ProcessPhysics
from sims.thread import SimThread
from sims.workpiece import Workpiece, rot
from sims.world import World

MAT = load_material("inconel718-1.0mm")


def _wall(gain: float, layers: int = 15) -> tuple[World, list[dict], float]:
    """A single-bead wall, 60 mm long, built open loop at the planned z (current follows the CTWD);
    its middle (past the pools at its ends, two bead widths each) at 20-40 mm."""
    w = World()
    phys = ProcessPhysics(MAT, ProcessSim(height_gain=gain))
    w.use_physics(phys)
    pp = inverse(MAT, 7.0)
    i_syn = synergic_current(MAT.ribeiro, pp.wfs_m_min)
    t = 0.0
    for L in range(layers):
        z = (L + 1) * pp.height_mm
        w.torch_moved("robot", 0, (0, 0, z + 10), (0, 0, z), t, t + 0.1)
        w.motion_stopped("robot")
        for k in range(30):
            stick = w.stick_out_mm()
            w.set_arc(True, phys.current_a(pp.wfs_m_min, stick if stick is not None else 15.0, i_syn), 20.0, t,
                      pp.wfs_m_min)
            dt = 2.0 / pp.speed_mm_min * 60.0
            w.torch_moved("robot", k + 1, (2.0 * k, 0, z), (2.0 * k + 2.0, 0, z), t, t + dt)
            w.motion_stopped("robot")
            t += dt
        w.set_arc(False, 0.0, 0.0, t)
    return w, w.segments, layers * pp.height_mm


def test_a_bead_on_a_plate_is_dings_parabola_holding_the_wire_metal():
    hm = HeightMap(0.25)
    hm.new_bead()
    hm.lay((0.0, 0.0), (30.0, 0.0), 6.0, 4.0)
    xs = np.arange(-4.0, 4.0, 0.25) + 0.125
    prof = np.array([hm.surface(15.1, y) for y in xs])
    area = float(np.sum(prof)) * 0.25
    assert area == pytest.approx(4.0, rel=0.02)                       # nothing lost, nothing twice
    assert prof.max() == pytest.approx(1.5 * 4.0 / 6.0, rel=0.03)     # Ding: area = 2/3·w·h
    assert hm.surface(15.1, 3.2) == 0.0                                # nothing outside w/2


def test_a_wall_with_gain_085_grows_lower_than_planned_and_its_ctwd_grows():
    w1, s1, planned = _wall(1.0)
    w85, s85, _ = _wall(0.85)
    top1 = w1.physics.maps["robot"].surface(30.1, 0.1)
    top85 = w85.physics.maps["robot"].surface(30.1, 0.1)
    assert top85 < planned - 1.0
    assert top85 == pytest.approx(0.85 * top1, rel=0.03)             # the metal scales with the gain
    mid = [s for s in s85 if 20.0 <= s["from"][0] < 40.0]
    per_layer = [mid[i]["ctwd_mm"] for i in range(0, len(mid), 10)]
    assert per_layer[-1] > per_layer[2] + 1.0                         # open loop: the torch drifts away
    assert all(b >= a - 0.05 for a, b in zip(per_layer[2:], per_layer[3:]))
    cur = [mid[i]["current_a"] for i in range(0, len(mid), 10)]
    assert cur[-1] < cur[2] - 2.0                                      # and the current falls with it
    assert all("bead_height_mm" in s for s in s85)
    # the truth in the row is the geometry: CTWD = stick-out + tool z − surface under the torch
    last = [s for s in s85 if s["from"][0] == 30.0][-1]
    top = w85.physics.maps["robot"].surface(31.0, 0.1)
    assert last["ctwd_mm"] == pytest.approx(15.0 + last["to"][2] - top, abs=0.15)


def test_the_probe_reads_the_grown_part_within_005_mm():
    phys = ProcessPhysics(MAT, ProcessSim())
    wp = Workpiece(np.asarray(_box_triangles(), dtype=float), rot((0, 0, 1), 0.0))
    phys.set_substrate("cnc", wp.top_z)
    wp.deposit_map = phys.height_map("cnc")
    w = World()
    w.use_physics(phys)
    pp = inverse(MAT, 7.0)
    t = 0.0
    w.set_arc(True, pp.current_a, 20.0, t, pp.wfs_m_min)
    for k in range(4):           # four overlapped beads, 30 mm long, on the block's top (z = 0)
        y = 5.165 * k
        dt = 30.0 / pp.speed_mm_min * 60.0
        w.torch_moved("cnc", k, (0, y, 0.77), (30, y, 0.77), t, t + dt,
                      part=((0.0, y, 0.77), (30.0, y, 0.77), (0.0, 0.0, 1.0)))
        w.motion_stopped("cnc")
        t += dt
    w.set_arc(False, 0.0, 0.0, t)
    hm = phys.maps["cnc"]
    for x, y in ((15.0, 5.165), (15.0, 7.5), (12.0, 10.33)):
        hit = wp.probe((x, y, 20.0), (x, y, -5.0))
        assert hit is not None
        assert hit[2] == pytest.approx(hm.surface(x, y), abs=0.05)
        assert hit[2] > 0.3                                   # on the deposit, not the block
        assert wp.inside((x, y, hit[2] - 0.1)) and not wp.inside((x, y, hit[2] + 0.1))
    off = wp.probe((-20.0, -20.0, 20.0), (-20.0, -20.0, -5.0))
    assert off is not None and off[2] == pytest.approx(0.0, abs=0.01)   # the block's own top


def _box_triangles() -> np.ndarray:
    import trimesh

    m = trimesh.creation.box(extents=(100, 100, 20))
    m.apply_translation((0.0, 0.0, -10.0))
    return np.asarray(m.triangles)


async def test_power_sim_current_falls_as_the_stick_out_grows_over_modbus():
    th = SimThread()
    world = World()
    phys = ProcessPhysics(MAT, ProcessSim())
    world.use_physics(phys)
    sim = PowerSourceSim(MAT, clock=SimClock(1.0), world=world, seed=1)
    url, close = th.run(serve_modbus_tcp(sim))
    ps = ModbusPowerSource(url, MAT, timeout_ms=SIM_REPLY_TIMEOUT_MS)
    try:
        await ps.connect()
        ps.set_wire_feed(6.0)
        arc = ArcHandshake(ps)
        await arc.start()
        means = []
        for z in (0.0, 3.0, 6.0):            # the tool point above the plate: CTWD 15, 18, 21 mm
            world.torch_moved("robot", 1, (0.0, 0.0, z), (0.0, 0.0, z), 0.0, 0.0)
            await asyncio.sleep(0.1)
            vals = [(await ps.next_status()).current_a for _ in range(20)]
            means.append(sum(vals) / len(vals))
        await arc.stop()
    finally:
        await ps.close()
        th.run(close())
        th.stop()
    i_syn = synergic_current(MAT.ribeiro, 6.0)
    assert means[0] == pytest.approx(i_syn, rel=0.01)        # nominal stick-out: the synergic line
    assert means[0] > means[1] + 5.0 > means[2] + 10.0       # about 2.5 A per mm at 133 A
    assert means[2] == pytest.approx(phys.current_a(6.0, 21.0), rel=0.01)


def _one_long_bead(defer: bool) -> World:
    """One 80 mm bead across a plate (a block's infill line), its segment closed at the end."""
    w = World(defer_lays=defer)
    w.use_physics(ProcessPhysics(MAT, ProcessSim()))
    pp = inverse(MAT, 6.0)
    w.set_arc(True, synergic_current(MAT.ribeiro, pp.wfs_m_min), 20.0, 0.0, pp.wfs_m_min)
    w.torch_moved("robot", 1, (0.0, 0.0, pp.height_mm), (80.0, 0.0, pp.height_mm), 0.0, 80.0 / pp.speed_mm_min * 60)
    w.motion_stopped("robot")
    return w


def test_a_deferred_long_bead_is_laid_a_piece_at_a_time_and_ends_as_one_laid_at_once():
    # The simulators lay deferred beads in their spare time, up to a deadline: a whole 80 mm bead
    # held their loop (the power source's and the cell I/O's replies) for 10-30 ms. It is now poured
    # 10 mm at a time, the deadline checked in between, into the same cells in the same order.
    now = _one_long_bead(defer=False)
    later = _one_long_bead(defer=True)
    unfinished = 0
    while not later.settle(deadline=time.perf_counter() + 1e-4):   # a step takes 0.5-2 ms
        unfinished += 1
        assert later._segments == [] and unfinished < 1000   # the row is logged once its bead is laid
    assert unfinished >= 7                       # 80 mm: 8 steps, at most one past each deadline
    assert later.segments == now.segments        # the same row, bead height included
    # the very same bead as one pour of the whole segment: no seam every 10 mm
    seg = now.segments[0]
    one = ProcessPhysics(MAT, ProcessSim())
    one.new_bead()
    one.lay("robot", tuple(seg["from"]), tuple(seg["to"]), seg["t1"] - seg["t0"], seg["current_a"],
            inverse(MAT, 6.0).wfs_m_min)
    grid = [(x, y) for x in np.arange(-4.0, 84.0, 0.25) for y in np.arange(-4.0, 4.0, 0.5)]
    whole = [one.maps["robot"].surface(x, y) for x, y in grid]
    # (the reference's times are the row's, rounded to 0.1 ms: 1e-5 mm apart at most; a seam was 0.29 mm)
    assert [later.physics.maps["robot"].surface(x, y) for x, y in grid] == pytest.approx(whole, abs=1e-4)
    assert [now.physics.maps["robot"].surface(x, y) for x, y in grid] == pytest.approx(whole, abs=1e-4)
    assert max(whole) > 0.5

"""Contract tests: the grbl driver (CncLink) against the CNC simulator over loopback TCP.

No mocks: the driver talks bytes through a real socket and the simulated 115200-baud line of
sims/transport.py; the simulator executes in simulated time and logs what it really ran.
"""
from __future__ import annotations

import asyncio
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from core.config import Workpiece as WorkpieceConfig
from core.config import load_cell, load_sim
from drivers.errors import LinkLost
from drivers.grbl import CncLink, GrblAckLost, GrblAlarm, GrblError, GrblReset, GrblStopped, GrblStuck, ProbeError
from sims.clock import SimClock
from sims.cnc import CncSim
from sims.cnc.block import Block
from sims.faults import parse_fault_spec
from sims.transport import SerialServer
from sims.up import SimContext, close_all
from sims.workpiece import Workpiece, rot
from sims.world import World

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


@dataclass
class Rig:
    sim: CncSim
    server: SerialServer
    link: CncLink
    world: World
    log: Path

    def executed(self) -> list[dict]:
        """The program's blocks the simulator executed (its log; the rig's homing cycle left out)."""
        self.sim.flush_log()
        return [e for e in map(json.loads, self.log.read_text().splitlines()) if e["verb"] != "$H"]


@pytest.fixture
async def rig_factory(tmp_path):
    made: list[Rig] = []

    async def make(*, time_scale: float = 200.0, noise: float = 0.0, faults: str = "",
                   link_timeout_s: float = 3.0, connect: bool = True, **wp) -> Rig:
        clock = SimClock(time_scale)
        world = World(tmp_path)
        wpc = WorkpieceConfig(**wp)
        piece = Workpiece.from_config(wpc, noise, seed=11)
        log = tmp_path / f"cnc{len(made)}.jsonl"
        sim = CncSim(clock=clock, world=world, workpiece=piece, log_path=log)
        sim.start()
        server = SerialServer(sim, name="cnc", spec=parse_fault_spec(faults), baud=115200)
        url = await server.start(None, ephemeral=True)
        link = CncLink(url, link_timeout_s=link_timeout_s)
        rig = Rig(sim, server, link, world, log)
        made.append(rig)
        if connect:
            await link.connect()
        return rig

    yield make
    for r in made:
        await r.link.close()
        await r.server.close()
        await r.sim.close()


async def ready(make, **kw) -> Rig:
    """A connected, homed machine."""
    r = await make(**kw)
    await r.link.home()
    return r


# -- connecting, locking, homing -----------------------------------------------------------------

async def test_power_up_is_locked_until_homed_or_unlocked(rig_factory):
    r = await rig_factory()
    link = r.link
    assert link.version == "1.1h"                 # the connect provoked the banner
    st = await link.status()
    assert st.state == "Alarm" and not link.homed  # $22=1: homing required after power-up
    with pytest.raises(GrblError) as exc:
        await link.command("G0 X10")
    assert exc.value.code == 9 and "locked out during alarm" in exc.value.meaning
    assert exc.value.line == "G0 X10"
    assert "[MSG:Caution: Unlocked]" in await link.unlock()
    assert (await link.status()).state == "Idle"
    await link.command("G0 X10")
    st = await link.wait_idle(20)
    assert st.mpos[0] == pytest.approx(10.0)
    assert not link.homed
    st = await link.home()
    assert link.homed and st.state == "Idle" and st.mpos[0] == pytest.approx(0.0)


async def test_system_commands_report_five_axes_and_settings(rig_factory):
    r = await ready(rig_factory)
    info = await r.link.command("$I")
    assert any("XYZAB" in s for s in info)
    settings = await r.link.command("$$")
    assert "$22=1" in settings and "$113=7200.000" in settings  # homing on; A-axis max rate
    gc = await r.link.command("$G")
    assert gc[0].startswith("[GC:G0 G54 G17 G21 G90")
    with pytest.raises(GrblError) as exc:
        await r.link.command("$BOGUS")
    assert exc.value.code == 3
    with pytest.raises(GrblError) as exc:
        await r.link.command("G2 X1 Y1 R5")      # arcs are not simulated: grbl's unsupported-command code
    assert exc.value.code == 20


# -- streaming -----------------------------------------------------------------------------------

def _program(n: int) -> list[str]:
    lines = ["G90 G21", "G1 F6000"]
    for i in range(n):
        lines.append(f"G1 X{(i * 7) % 40}.{i % 10} Y{i * 0.05:.2f} Z{(i % 5) * 0.2:.1f}")  # all distinct
    return lines


async def test_stream_keeps_the_buffer_full_and_runs_every_line_once(rig_factory):
    # motion-bound (the machine, not the 115200-baud line, is the bottleneck), as on a real job
    r = await ready(rig_factory, time_scale=25.0)
    prog = _program(250)
    seen: list[tuple[int, int]] = []
    res = await r.link.stream(prog, progress=lambda a, s: seen.append((a, s)))
    assert res.lines == len(prog) and res.acked == len(prog)
    # character counting: never more than grbl's 127 usable bytes, and close to full on average
    assert res.max_in_flight_bytes <= 127
    assert res.mean_in_flight_bytes > 0.75 * 127
    assert r.sim.rx_dropped == 0
    assert seen[-1] == (len(prog), len(prog))
    # the simulator ran each line once, in order, and the stream returned only after the last
    ran = [e for e in r.executed() if e["line"] != "G4P0"]
    assert [e["line"] for e in ran] == [ln.replace(" ", "") for ln in prog]
    st = await r.link.status()
    assert st.state == "Idle"
    assert st.mpos[:3] == pytest.approx(ran[-1]["target"], abs=1e-3)


async def test_stream_stops_at_the_first_error_and_names_the_line(rig_factory):
    r = await ready(rig_factory)
    prog = _program(400)
    bad = 250                                    # 1-based line number of the faulty line
    prog[bad - 1] = "G1 X5 Y5 W3"               # W is not a grbl word
    prog[300] = "G1 X1 Q9"                      # a later error must not be the one reported
    with pytest.raises(GrblError) as exc:
        await r.link.stream(prog)
    e = exc.value
    assert e.line_number == bad and e.line == "G1 X5 Y5 W3" and e.code == 20
    assert f"line {bad}" in str(e) and "error:20" in str(e)
    await r.link.wait_idle(20)
    ran = [x["line"] for x in r.executed()]
    # sending stopped at the error: only what was already in grbl's 127-byte buffer ran after it
    after = len(ran) - ran.index(prog[bad - 2].replace(" ", "")) - 1
    assert 0 <= after <= 127 // 10
    assert prog[-1].replace(" ", "") not in ran
    # the link is still usable
    await r.link.command("G0 X0 Y0")


async def test_rx_buffer_is_really_bounded_without_character_counting(rig_factory):
    # What character counting prevents: grbl's RX ring holds 127 bytes and loses the rest
    # while the planner is full. Bytes pushed in at once, as a naive sender would.
    r = await ready(rig_factory, time_scale=1.0)
    flood = "".join(f"G1 X{i} F60\n" for i in range(1, 60)).encode()
    r.sim.feed(flood)
    await asyncio.sleep(0.2)
    assert r.sim.rx_dropped > 0
    assert r.sim.rx_fill <= 127


async def test_lines_that_cannot_fit_grbls_buffer_are_refused_before_sending(rig_factory):
    r = await ready(rig_factory)
    from core.errors import InputError
    with pytest.raises(InputError, match="line 2"):
        await r.link.stream(["G0 X1", "G1 X" + "1" * 130])
    assert r.sim.machine.lines_received == 0


# -- real-time commands --------------------------------------------------------------------------

async def test_feed_hold_stops_motion_and_resume_finishes_it(rig_factory):
    r = await ready(rig_factory, time_scale=5.0)
    await r.link.command("G1 X200 F3000")        # 4 s of process time, 0.8 s wall
    await asyncio.sleep(0.25)
    await r.link.feed_hold()
    for _ in range(20):
        st = await r.link.status()
        if st.state == "Hold" and st.substate == 0:
            break
    assert st.state == "Hold" and st.substate == 0
    x_held = st.mpos[0]
    assert 1.0 < x_held < 199.0
    await asyncio.sleep(0.3)
    assert (await r.link.status()).mpos[0] == pytest.approx(x_held)   # nothing moves while held
    await r.link.resume()
    st = await r.link.wait_idle(20)
    assert st.mpos[0] == pytest.approx(200.0)


async def test_soft_reset_in_motion_raises_alarm_3_and_flushes(rig_factory):
    r = await ready(rig_factory, time_scale=2.0)
    stream = asyncio.ensure_future(r.link.stream([f"G1 X{i * 5} F600" for i in range(1, 40)]))
    await asyncio.sleep(0.5)
    await r.link.soft_reset()
    with pytest.raises((GrblReset, GrblAlarm)):
        await stream
    st = await r.link.status()
    assert st.state == "Alarm" and 3 in r.link.alarms and not r.link.homed
    x = st.mpos[0]
    await asyncio.sleep(0.3)
    assert (await r.link.status()).mpos[0] == x   # the rest of the program was flushed
    await r.link.home()


async def test_safe_stop_from_another_thread_while_streaming(rig_factory):
    # what the controller's signal / fault path does: a thread that is not the link's loop
    r = await ready(rig_factory, time_scale=5.0)
    await r.link.command("$32=1")
    stream = asyncio.ensure_future(r.link.stream(["G1 F600", "M3 S800"] + [f"G1 X{i * 3} Y{i % 2}" for i in range(1, 60)]))
    while (st := await r.link.status()).state != "Run" or st.spindle == 0:
        assert not stream.done()
    results = await asyncio.gather(asyncio.to_thread(r.link.safe_stop_threadsafe, "SIGTERM"),
                                   r.link.safe_stop("a second signal"))       # joins the first stop
    assert results[0] is results[1] and results[0].reason in ("SIGTERM", "a second signal")   # one stop, not two
    res = results[0]
    assert res.verified and res.reset and res.held and not res.needs_unlock, (res.problems, res.steps)
    with pytest.raises(GrblStopped):
        await stream
    x = (await r.link.status()).mpos[0]
    await asyncio.sleep(0.3)
    st = await r.link.status()
    assert st.state == "Idle" and st.mpos[0] == x and st.spindle == 0 and st.accessories == ""
    ran = [e["line"] for e in r.executed()]
    assert ran[-1] != "G1X177Y0" and "M5" not in ran     # the rest was flushed, not run
    await r.link.command("G0 X0")                         # usable again, no $X needed


async def test_safe_stop_that_cannot_wait_for_the_hold_resets_in_motion_and_says_so(rig_factory):
    r = await ready(rig_factory, time_scale=2.0)
    stream = asyncio.ensure_future(r.link.stream(["G1 F3000", "M3 S500"] + [f"G1 X{i * 20}" for i in range(1, 20)]))
    while (await r.link.status()).state != "Run":
        assert not stream.done()
    res = await r.link.safe_stop("fault", hold_timeout_s=0.0)     # no time to decelerate
    with pytest.raises(GrblStopped):
        await stream
    assert "hold" in res.timed_out and res.reset and res.alarm == 3
    assert res.needs_unlock and res.needs_homing and res.state == "Alarm" and res.verified
    assert not r.link.homed
    with pytest.raises(GrblError) as e:                  # left alarmed, as reported: G-code locked out
        await r.link.command("G0 X0")
    assert e.value.code == 9


# -- probing -------------------------------------------------------------------------------------

def _top_z(x: float, y: float, a_deg: float, b_deg: float, c_deg: float = 0.0) -> float:
    m = rot((0, 1, 0), b_deg) @ rot((1, 0, 0), a_deg) @ rot((0, 0, 1), c_deg)
    n = m[:3, 2]
    return -(n[0] * x + n[1] * y) / n[2]


async def test_probing_finds_the_tilted_top_face(rig_factory):
    r = await ready(rig_factory, noise=0.002, tilt_a_deg=2.0, tilt_b_deg=-1.0, rotation_c_deg=1.5)
    pts = []
    for x, y in [(-30, -30), (30, -30), (30, 30), (-30, 30), (0, 0)]:
        await r.link.command(f"G0 X{x} Y{y} Z10")
        res = await r.link.probe((x, y, -15), 200)
        assert res.contact
        assert res.position[2] == pytest.approx(_top_z(x, y, 2.0, -1.0, 1.5), abs=0.012)
        st = await r.link.status()
        assert st.probe_tripped and st.state == "Idle"
        pts.append(res.position[:3])
        await r.link.command("G91 G0 Z2")
        await r.link.command("G90")
        assert not (await r.link.status()).probe_tripped
    # the plane through the probed points is the configured tilt
    p = np.array(pts)
    normal = np.linalg.svd(p - p.mean(axis=0))[2][2]
    normal = normal if normal[2] > 0 else -normal
    tilt = math.degrees(math.acos(normal[2]))
    expect = math.degrees(math.acos((rot((0, 1, 0), -1.0) @ rot((1, 0, 0), 2.0))[2, 2]))
    assert tilt == pytest.approx(expect, abs=0.05)


async def test_probe_noise_is_seeded_and_sized_by_config(rig_factory):
    r = await ready(rig_factory, noise=0.01)
    zs = []
    for _ in range(12):
        await r.link.command("G0 X10 Y10 Z3")
        zs.append((await r.link.probe((10, 10, -5), 300)).position[2])
    spread = float(np.std(zs))
    assert 0.003 < spread < 0.03                 # σ = 0.01 mm, reported to 0.001 mm


async def test_rotary_table_levels_the_part(rig_factory):
    # The A/B table carries the part: turning A by -tilt_a brings the top face level.
    r = await ready(rig_factory, tilt_a_deg=3.0)
    await r.link.command("G0 X0 Y40 Z10")
    tilted = (await r.link.probe((0, 40, -20), 300)).position[2]
    assert tilted == pytest.approx(40 * math.tan(math.radians(3.0)), abs=0.01)
    await r.link.command("G0 Z10")
    await r.link.command("G0 A-3")
    leveled = (await r.link.probe((0, 40, -20), 300)).position[2]
    assert leveled == pytest.approx(0.0, abs=0.01)
    assert (await r.link.status()).mpos[3] == pytest.approx(-3.0)


async def test_probe_failures_raise_grbl_alarms_4_and_5(rig_factory):
    r = await ready(rig_factory)
    await r.link.command("G0 X200 Y0 Z5")        # beside the 100 mm block
    with pytest.raises(ProbeError) as exc:
        await r.link.probe({"z": -10}, 300)
    assert exc.value.code == 5 and "Z-10.000" in str(exc.value)
    assert (await r.link.status()).state == "Idle"  # unlocked again: probe alarms keep position
    miss = await r.link.probe({"z": -15}, 300, mode="G38.3")
    assert not miss.contact and miss.position[2] == pytest.approx(-15.0)
    await r.link.command("G0 Z5")
    await r.link.command("G0 X0")
    hit = await r.link.probe({"z": -5}, 300)
    assert hit.contact
    with pytest.raises(ProbeError) as exc:        # still touching: ALARM:4
        await r.link.probe({"z": -6}, 300)
    assert exc.value.code == 4
    assert 4 in r.link.alarms and 5 in r.link.alarms


# -- the link ------------------------------------------------------------------------------------

async def test_stream_over_a_slow_laggy_line_still_runs_every_line(rig_factory):
    # seeded fault channel: 4 ms one-way latency and a 57600-baud line
    r = await ready(rig_factory, faults="seed=7,latency=4ms,baud=57600")
    prog = _program(120)
    res = await r.link.stream(prog)
    assert res.acked == len(prog) and r.sim.rx_dropped == 0
    assert res.max_in_flight_bytes <= 127 and res.mean_in_flight_bytes > 60
    ran = [e["line"] for e in r.executed() if e["line"] != "G4P0"]
    assert ran == [ln.replace(" ", "") for ln in prog]


@pytest.mark.parametrize("seed", [1, 2, 3])
async def test_corrupting_line_never_hangs_the_driver(rig_factory, seed):
    # grbl has no checksums: corrupted bytes become refused lines (error:N), lost 'ok's (the
    # driver sees grbl idle with lines unanswered) or, rarely, a different valid line. Whatever
    # happens, the stream ends promptly, with success or an error that names the device.
    from drivers.errors import DeviceError
    r = await rig_factory(faults=f"seed={seed},corrupt=0.001")
    try:
        await r.link.unlock()
    except DeviceError as exc:  # the corruption hit the unlock's own reply: named, not hung
        assert r.link.url in str(exc)
        return
    t0 = asyncio.get_running_loop().time()
    task = asyncio.ensure_future(r.link.stream(_program(300)))
    while not task.done() and asyncio.get_running_loop().time() - t0 < 30:
        await asyncio.wait([task], timeout=1.0)
        st = r.link.latest_status
        if not task.done() and st is not None and st.state == "Hold":
            await r.link.resume()   # a '1' flipped into '!' is a feed hold: the operator resumes
    assert task.done(), "the stream hung on a corrupted line"
    try:
        assert task.result().acked == 302
    except DeviceError as exc:
        assert r.link.url in str(exc)


async def test_silent_port_is_link_lost(rig_factory):
    r = await ready(rig_factory, link_timeout_s=1.0)
    r.server.stall(5.0)                           # the cable carries nothing for 5 s
    with pytest.raises(LinkLost):
        for _ in range(30):
            await r.link.status()
    with pytest.raises(LinkLost):
        await r.link.command("G0 X1")


async def test_firmware_starved_while_idle_is_not_a_lost_ok(rig_factory):
    # A firmware that reported Idle and then gets no CPU for 3.5 s (longer than the 2 s ack grace,
    # shorter than the link timeout) answers late, not never: the line must complete, not fail
    # as a lost 'ok' (CI saw this on grblHAL's simulator beside another test worker).
    r = await ready(rig_factory, link_timeout_s=8.0)
    assert (await r.link.status()).state == "Idle"
    r.server.stall(3.5)
    t0 = asyncio.get_running_loop().time()
    await r.link.command("G90")
    assert asyncio.get_running_loop().time() - t0 > 3.0
    assert (await r.link.status()).state == "Idle"


async def test_lost_ok_with_grbl_idle_is_named(rig_factory):
    # grbl has no checksums: an 'ok' lost on the line leaves the driver waiting while grbl keeps
    # reporting Idle. The driver names it (GrblAckLost) instead of waiting for ever.
    r = await ready(rig_factory, link_timeout_s=8.0)
    assert (await r.link.status()).state == "Idle"
    outbound = r.server.pipes[1]
    outbound.drop = 1.0                       # everything grbl says is lost for 0.3 s: the 'ok' too
    task = asyncio.ensure_future(r.link.command("G90"))
    await asyncio.sleep(0.3)
    outbound.drop = 0.0
    t0 = asyncio.get_running_loop().time()
    with pytest.raises(GrblAckLost, match="never acknowledged"):
        await asyncio.wait_for(task, 6.0)
    assert asyncio.get_running_loop().time() - t0 < r.link.ack_grace_s + 1.0


async def test_firmware_that_stops_reading_is_named_not_waited_for(rig_factory):
    # grbl keeps answering '?' (its serial interrupt) while its main loop reads nothing more: with
    # Bf: in the reports the driver sees its line still in grbl's RX buffer. That is not a lost
    # 'ok' (nothing was answered yet), and it is not waited for for ever either: GrblStuck.
    r = await ready(rig_factory, link_timeout_s=10.0)
    await r.link.command("$10=3")             # status reports with Bf: (grblHAL's default)
    r.link.stuck_after_s = 3.0                # longer than the lost-'ok' grace (2 s): that must not fire
    st = await r.link.status()
    assert st.rx_free is not None
    r.sim.hung = True
    t0 = asyncio.get_running_loop().time()
    with pytest.raises(GrblStuck, match=r"4 byte\(s\) of ours unread .* from 'G90' on unanswered"):
        await asyncio.wait_for(r.link.command("G90"), 8.0)
    assert asyncio.get_running_loop().time() - t0 < r.link.stuck_after_s + 1.5


async def test_unplugged_cable_is_link_lost(rig_factory):
    r = await ready(rig_factory)
    await r.link.command("G0 X12")
    await r.link.wait_idle(10)
    r.server.unplug(0.5)
    with pytest.raises(LinkLost):
        await r.link.command("G4 P0")
        for _ in range(30):
            await r.link.status()
    # plugged back in: the controller kept its state (homed, position), the driver reconnects
    await asyncio.sleep(0.6)
    st = await r.link.connect()
    assert st.state == "Idle" and st.mpos[0] == pytest.approx(12.0)
    await r.link.command("G0 X0")


async def test_served_by_sim_up_with_exec_log_and_world(tmp_path):
    # The CNC simulator as `cell sim up` starts it, coupled to the World.
    cell, simcfg = load_cell(), load_sim()
    world = World(tmp_path)
    ctx = SimContext(cell=cell, sim=simcfg, world=world, clock=SimClock(200.0), log_dir=tmp_path,
                     ephemeral=True)
    from sims import cnc as cnc_sim
    served = await cnc_sim.serve(ctx)
    try:
        (s,) = served
        assert s.device == "cnc" and s.url.startswith("socket://127.0.0.1:")
        link = CncLink(s.url)
        await link.connect()
        z0 = (await link.home()).mpos[2]
        world.set_arc(True, 120.0, 20.0, ctx.clock.now())   # the process is on
        await link.stream(["G1 F3000", "M3 S500", "G1 X10", "G1 X10 Y10", "M5"])
        world.set_arc(False, 0.0, 0.0, ctx.clock.now())
        await link.close()
    finally:
        await close_all(served)
    log = [json.loads(x) for x in (tmp_path / "cnc.jsonl").read_text().splitlines()]
    assert [e["verb"] for e in log[-5:]] == ["M3", "G1", "G1", "M5", "G4"]
    assert log[-4]["target"] == [10.0, 0.0, z0] and log[-3]["target"] == [10.0, 10.0, z0]
    assert all({"seq", "verb", "target", "t", "line"} <= set(e) for e in log)
    segs = [x for x in world.segments if x["device"] == "cnc"]
    assert [s_["to"] for s_ in segs][-2:] == [[10.0, 0.0, z0], [10.0, 10.0, z0]]


def test_workpiece_from_a_mesh_file_is_posed_and_probed(tmp_path):
    import trimesh

    cyl = trimesh.creation.cylinder(radius=20.0, height=30.0, sections=64)  # z ∈ [-15, 15]
    path = tmp_path / "boss.stl"
    cyl.export(path)
    wpc = WorkpieceConfig(mesh="boss.stl", offset_mm=(5.0, 0.0, 10.0), tilt_a_deg=0.0)
    wp = Workpiece.from_config(wpc, 0.0, base_dir=tmp_path)
    # top face at z = 15 + 10, probing straight down over the (shifted) axis
    hit = wp.probe((5.0, 0.0, 60.0), (5.0, 0.0, 0.0))
    assert hit is not None and hit[2] == pytest.approx(25.0, abs=1e-6)
    # from the side along -X: the cylinder wall at x = 5 + 20
    side = wp.probe((60.0, 0.0, 10.0), (0.0, 0.0, 10.0))
    assert side is not None and side[0] == pytest.approx(25.0, abs=0.1)
    assert wp.inside((5.0, 0.0, 10.0)) and not wp.inside((5.0, 0.0, 26.0))
    assert wp.probe((60.0, 60.0, 60.0), (60.0, 60.0, 0.0)) is None     # misses the part
    # the table's A axis carries the part: turned 90° about X, the top now faces -Y
    assert wp.surface_hit((5.0, -60.0, 0.0), (5.0, 0.0, 0.0), 90.0, 0.0) == pytest.approx(35.0, abs=1e-6)


def test_a_probing_move_that_ends_within_one_tick_stops_at_the_surface(tmp_path):
    # a loaded host (or a high time scale) lets one executor tick cover the whole probing move:
    # it must still end where the stylus touches, not at the commanded end inside the part (the
    # next touch then started inside it: ALARM:4, 1 alignment in 3 under make test)
    piece = Workpiece.from_config(WorkpieceConfig(), 0.0, seed=11)
    sim = CncSim(clock=SimClock(60.0), workpiece=piece, log_path=tmp_path / "cnc.jsonl", homing_enabled=False)
    top = float(piece.top_z(np.array([0.0]), np.array([0.0]))[0])
    sim.machine.pos = [0.0, 0.0, top + 5.0, 0.0, 0.0]
    b = Block(1, "G38.2", "G38.2 Z-10 F300", target=(0.0, 0.0, top - 10.0, 0.0, 0.0), feed=300.0, probe="G38.2")
    sim.machine.push(b)
    sim.advance(0.0, 1000.0)                          # far more process time than the move needs
    assert b.done and b.contact
    assert abs(sim.machine.pos[2] - top) < 1e-6, sim.machine.pos      # on the surface, not 10 mm into the part
    assert not piece.inside(tuple(sim.machine.pos[:3]), 0.0, 0.0)

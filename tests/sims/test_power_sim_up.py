"""The power source and cell I/O as `cell sim up` serves them: coupled through the World."""
from __future__ import annotations

import asyncio
import json
from contextlib import asynccontextmanager

import pytest

from controller.runtime.arc_handshake import ArcHandshake, ArcLost
from controller.defaults import SIM_REPLY_TIMEOUT_MS
from core.config import load_cell, load_material, load_sim
from drivers.registry import open_cellio, open_power_source
from sims.clock import SimClock
from sims.up import SimContext, close_all, serve_all
from sims.world import World


@asynccontextmanager
async def sim_up(tmp_path, faults: str = ""):
    cell, sim = load_cell(), load_sim()
    mat = load_material(cell.cell.material)
    world = World(tmp_path, arc_efficiency=mat.arc_efficiency)
    ctx = SimContext(cell=cell, sim=sim, world=world, clock=SimClock(cell.cell.time_scale), log_dir=tmp_path,
                     ephemeral=True, faults=faults)
    served = await serve_all(ctx, ["sims.power_sim", "sims.cellio_sim"])
    urls = {s.device: s for s in served}
    # the simulators are served on this test's own loop: they share its GIL, as with `--sim`
    ps_cfg = cell.devices.power_source.model_copy(update={"timeout_ms": SIM_REPLY_TIMEOUT_MS})
    ps = open_power_source(ps_cfg, mat, url=urls["power_source"].url)
    io = open_cellio(cell.devices.cellio, url=urls["cellio"].url, timeout_ms=SIM_REPLY_TIMEOUT_MS)
    await ps.connect()
    await io.connect()
    try:
        yield ctx, urls, ps, io
    finally:
        await io.close()
        await ps.close()
        await close_all(served)
        world.close()


async def test_metal_only_where_the_torch_moves_while_the_arc_is_stable(tmp_path):
    async with sim_up(tmp_path) as (ctx, urls, ps, io):
        world, clock = ctx.world, ctx.clock
        t = clock.now()
        world.torch_moved("robot", 1, (0, 0, 0), (10, 0, 0), t, t + 0.1)     # travel, arc off
        world.motion_stopped("robot")
        t_before = (await io.next_inputs()).part_temperature_c
        ps.set_wire_feed(6.0)
        arc = ArcHandshake(ps)
        await arc.start()
        for k in range(10):                                                  # a 20 mm bead
            t = clock.now()
            world.torch_moved("robot", 2, (10 + 2 * k, 0, 0), (12 + 2 * k, 0, 0), t, t + 0.05)
            await asyncio.sleep(0.02)
        world.motion_stopped("robot")
        await asyncio.sleep(0.3)
        await arc.stop()
        t_after = (await io.next_inputs()).part_temperature_c
        world.flush()
        segs = [json.loads(x) for x in (tmp_path / "deposit.jsonl").read_text().splitlines()]
        assert len(segs) == 1
        s = segs[0]
        assert s["from"] == [10.0, 0.0, 0.0] and s["to"] == [30.0, 0.0, 0.0]
        i_expect = 95 + (6.0 - 4.0) * (160 - 95) / (7.4 - 4.0)
        assert s["current_a"] == pytest.approx(i_expect, rel=0.03)
        assert s["voltage_v"] == pytest.approx(13.5 + 1.2 * 6.0, rel=0.03)
        assert t_after > t_before + 5.0, "the part heats while the arc burns"


async def test_fault_spec_arc_loss_at_a_time(tmp_path):
    async with sim_up(tmp_path, faults="arc_loss@t=40s,arc_loss=600ms") as (ctx, urls, ps, io):
        ps.set_wire_feed(6.0)
        arc = ArcHandshake(ps)
        await arc.start()
        wait_s = max(0.0, (40.0 - ctx.clock.now()) / ctx.clock.time_scale)
        await asyncio.wait_for(arc.faulted.wait(), wait_s + 1.5)
        assert isinstance(arc.fault, ArcLost)
        sim = urls["power_source"].sim
        inj = [e for e in sim.log if e["event"] == "inject"]
        assert inj and inj[0]["t_sim"] == pytest.approx(40.0, abs=1.5)


async def test_fault_spec_ignition_failure_probability_one_exhausts_the_retries(tmp_path):
    from controller.runtime.arc_handshake import IgnitionFailed
    async with sim_up(tmp_path, faults="seed=3,ignition_fail=1.0") as (ctx, urls, ps, io):
        ps.set_wire_feed(6.0)
        arc = ArcHandshake(ps, ignition_timeout_s=0.2, ignition_retries=1)
        with pytest.raises(IgnitionFailed, match="2 attempts"):
            await arc.start()
        assert urls["power_source"].sim.starts == 2


@pytest.mark.parametrize("transport", ["modbus_rtu", "can"])
async def test_sim_up_serves_the_configured_transport(tmp_path, transport):
    import uuid
    cell = load_cell()
    dev = cell.devices.power_source
    upd = {"transport": transport}
    if transport == "modbus_rtu":
        upd["url"] = "socket://127.0.0.1:0"
    else:
        upd["can"] = dev.can.model_copy(update={"interface": "virtual", "channel": f"up-{uuid.uuid4().hex[:8]}"})
    dev = dev.model_copy(update=upd)
    cell = cell.model_copy(update={"devices": cell.devices.model_copy(update={"power_source": dev})})
    world = World(tmp_path)
    ctx = SimContext(cell=cell, sim=load_sim(), world=world, clock=SimClock(60.0), ephemeral=True)
    served = await serve_all(ctx, ["sims.power_sim"])
    try:
        s = served[0]
        assert s.describe()["transport"] == transport
        ps = open_power_source(dev, load_material(), url=s.url if transport == "modbus_rtu" else None)
        await ps.connect()
        try:
            ps.set_wire_feed(6.0)
            arc = ArcHandshake(ps)
            await arc.start()
            assert ps.status.current_a == pytest.approx(133.2, rel=0.05) and world.arc_stable
            await arc.stop()
        finally:
            await ps.close()
    finally:
        await close_all(served)


async def test_can_between_processes_over_udp_multicast():
    """`cell sim up` and the controller are two processes: CAN frames cross over udp_multicast."""
    import random
    import subprocess
    import sys
    from pathlib import Path
    from drivers.power_can import CanPowerSource
    port = random.randint(43200, 43999)
    proc = subprocess.Popen([sys.executable, "-m", "bench._power_sim_proc", "can", "239.74.163.11", str(port)],
                            cwd=Path(__file__).resolve().parents[2], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        line = await asyncio.get_running_loop().run_in_executor(None, proc.stdout.readline)
        assert line.startswith("can://udp_multicast/")
        ps = CanPowerSource(interface="udp_multicast", channel="239.74.163.11", port=port,
                            material=load_material(), timeout_ms=SIM_REPLY_TIMEOUT_MS)
        await ps.connect()
        try:
            ps.set_wire_feed(6.0)
            arc = ArcHandshake(ps)
            await arc.start()
            assert ps.status.arc_stable and ps.status.voltage_v == pytest.approx(20.7, rel=0.05)
            await arc.stop()
        finally:
            await ps.close()
    finally:
        proc.stdin.close()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()

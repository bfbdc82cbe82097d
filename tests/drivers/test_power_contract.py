"""The PowerSource contract, run against the simulator over Modbus TCP, Modbus RTU and CAN."""
from __future__ import annotations

import asyncio
import time

import pytest

from drivers.errors import DeviceError, LinkLost
from drivers.power import CommandRangeError
from drivers.power_modbus import ModbusPowerSource
from wire.power_registers import POWER_MAP, Register, RegisterMap
from core.errors import CellError
from tests.power_fixtures import MATERIAL, TRANSPORTS, power_rig, wait_for


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_commands_reach_the_device_scaled_and_watchdog_increments(transport):
    async with power_rig(transport) as (th, sim, ps, _):
        ps.set_job(mode=1, job=7)
        ps.set_wire_feed(6.25)
        ps.set_trims(arc=-3.4, dynamic=2.1)
        for _ in range(5):
            await ps.next_status()
        c = th.call(lambda: sim.cmd)
        assert (c.mode, c.job) == (1, 7)
        assert c.wfs == pytest.approx(6.25, abs=0.005)
        assert c.arc_trim == pytest.approx(-3.4, abs=0.05)
        assert c.dynamic_trim == pytest.approx(2.1, abs=0.05)
        counters = [h[1] for h in th.call(lambda: list(sim.history))]
        steps = {(b - a) % ps.COUNTER_MOD for a, b in zip(counters, counters[1:])}
        assert steps == {1}, "the host must increment the watchdog counter every cycle"
        st = ps.status
        assert st.watchdog_ok and st.collision_ok and not st.process_active


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_start_bits_are_cleared_on_connect(transport):
    async with power_rig(transport, connect=False) as (th, sim, ps, _):
        ps.set_weld_start(True)          # left over from before a restart
        ps.set_gas_test(True)
        await ps.connect()
        first_bits = th.call(lambda: sim.history[0][2])
        assert not any(first_bits.values()), first_bits
        await ps.next_status()
        assert th.call(lambda: sim.phase) == "idle"


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_weld_gives_synergic_actuals(transport):
    async with power_rig(transport) as (th, sim, ps, world):
        ps.set_robot_ready(True)
        ps.set_wire_feed(5.7)            # midway on Inconel's synergic line: 95..160 A over 4.0..7.4 m/min
        ps.set_trims(arc=2.0)
        ps.set_weld_start(True)
        st = await wait_for(ps, lambda s: s.motion_release)
        assert st.arc_stable and st.current_flow and st.process_active
        samples = [await ps.next_status() for _ in range(10)]
        i = sum(s.current_a for s in samples) / 10
        u = sum(s.voltage_v for s in samples) / 10
        assert i == pytest.approx(127.5, rel=0.03)
        assert u == pytest.approx(13.5 + 1.2 * 5.7 + 0.3 * 2.0, rel=0.03)
        assert samples[-1].wfs_m_min == pytest.approx(5.7, abs=0.01)
        assert world.arc_stable and world.current_a == pytest.approx(127.5, rel=0.05)
        ps.set_weld_start(False)
        st = await wait_for(ps, lambda s: not s.process_active)
        assert st.current_a == 0 and not world.arc_stable


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_out_of_range_commands_are_refused_before_sending(transport):
    async with power_rig(transport) as (th, sim, ps, _):
        ps.set_wire_feed(6.0)
        with pytest.raises(CommandRangeError, match=r"7\.5 m/min.*WFSmax"):
            ps.set_wire_feed(7.5)
        with pytest.raises(CommandRangeError, match="arc-length trim"):
            ps.set_trims(arc=10.5)
        with pytest.raises(CommandRangeError, match="dynamic trim"):
            ps.set_trims(dynamic=-5.1)
        with pytest.raises(CommandRangeError, match="mode"):
            ps.set_job(mode=3)
        for _ in range(3):
            await ps.next_status()
        assert th.call(lambda: sim.cmd.wfs) == pytest.approx(6.0, abs=0.005)


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_error_reset_is_an_edge_that_clears_a_latched_fault(transport):
    async with power_rig(transport) as (th, sim, ps, _):
        th.call(sim.inject, "gas_fault")
        st = await wait_for(ps, lambda s: s.gas_fault)
        assert st.error_number == 10 and not st.ready
        for _ in range(3):                # the fault stays latched while nobody resets it
            assert (await ps.next_status()).gas_fault
        st = await ps.error_reset()
        assert not st.gas_fault and st.error_number == 0
        assert not st.command.error_reset, "the reset bit must fall again (edge)"


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_wire_inch_and_retract(transport):
    async with power_rig(transport) as (th, sim, ps, _):
        ps.set_wire_feed(2.0)
        ps.set_wire_inch(True)
        st = await wait_for(ps, lambda s: s.wfs_m_min > 0)
        assert st.wfs_m_min == pytest.approx(2.0, abs=0.01) and st.current_a == 0
        ps.set_wire_retract(True)
        st = await wait_for(ps, lambda s: s.wfs_m_min < 0)
        assert st.wfs_m_min == pytest.approx(-2.0, abs=0.01) and not st.command.wire_inch


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_silent_device_is_a_lost_link_naming_the_url(transport):
    async with power_rig(transport, timeout_ms=150) as (th, sim, ps, _):
        lost = []
        ps.on_error(lost.append)
        await ps.next_status()
        th.call(sim.inject, "silence")
        t0 = time.monotonic()
        with pytest.raises(LinkLost) as ei:
            for _ in range(50):
                await ps.next_status()
        assert time.monotonic() - t0 < 1.0
        msg = str(ei.value)
        assert "no reply within 150 ms" in msg
        assert (ps.url in msg) or ("channel" in msg)
        assert lost and lost[0] is ei.value
        ps.set_weld_start(False)          # dropping the start is still accepted
        with pytest.raises(LinkLost):
            await ps.next_status()


async def test_nothing_listening_is_a_lost_link():
    ps = ModbusPowerSource("tcp://127.0.0.1:1", MATERIAL)
    with pytest.raises(LinkLost, match=r"tcp://127\.0\.0\.1:1.*cannot connect"):
        await ps.connect()


async def test_wrong_register_map_is_named_by_the_driver():
    shifted = RegisterMap(command_start=0xF010, command_count=POWER_MAP.command_count,
                          status_start=POWER_MAP.status_start, status_count=POWER_MAP.status_count,
                          registers=tuple(Register(r.name, r.address + (0x10 if r.direction == "command" else 0),
                                                   r.kind, r.scale, r.direction) for r in POWER_MAP.registers))
    async with power_rig("modbus_tcp", connect=False) as (th, sim, ps, _):
        bad = ModbusPowerSource(ps.url, MATERIAL, register_map=shifted)
        with pytest.raises(DeviceError, match=r"register map.*0xF010"):
            await bad.connect()


def test_register_map_entry_outside_its_block_is_a_clear_error():
    regs = list(POWER_MAP.registers)
    regs[2] = Register("mode", 0xF020, "u16")
    bad = RegisterMap(POWER_MAP.command_start, POWER_MAP.command_count, POWER_MAP.status_start,
                      POWER_MAP.status_count, tuple(regs))
    with pytest.raises(CellError, match=r"'mode' at 0xF020 is outside the command block 0xF000\.\.0xF00D"):
        bad.validate()


def test_design_register_addresses():
    addr = {r.name: r.address for r in POWER_MAP.registers}
    assert addr["watchdog"] == 0xF000 and addr["command_bits"] == 0xF001
    assert (addr["mode"], addr["job"], addr["wfs_command"]) == (0xF008, 0xF009, 0xF00B)
    assert (addr["voltage"], addr["current"], addr["wfs_actual"]) == (0xF10A, 0xF10B, 0xF110)


async def test_device_watchdog_drops_the_start_when_the_host_stops_cycling():
    async with power_rig("modbus_tcp") as (th, sim, ps, _):
        ps.set_robot_ready(True)
        ps.set_wire_feed(6.0)
        ps.set_weld_start(True)
        await wait_for(ps, lambda s: s.arc_stable)
        time.sleep(0.25)                  # the host loop hangs: no cycle, no new counter
        assert th.call(lambda: sim.phase) == "idle", "the device must drop the start on its watchdog"
        st = await ps.next_status()
        assert st.error_number == 50 and not st.arc_stable and st.command.weld_start


def test_can_frames_follow_the_dbc():
    import cantools
    from drivers.power import PowerCommand
    from wire.can_codec import DEFAULT_DBC, CanCodec
    codec = CanCodec(cantools.database.load_file(str(DEFAULT_DBC)), node=3)
    assert (codec.cmd_id, codec.sta_id, codec.act_id) == (0x203, 0x183, 0x283)
    data = codec.encode_command(PowerCommand(weld_start=True, job=7, wfs_m_min=6.25, arc_trim=-3.4), 42)
    assert data[0] & 1 and data[1] == 7 and int.from_bytes(data[2:4], "little", signed=True) == 625
    assert data[4] == (-34) & 0xFF and data[6] == 42
    back = codec.decode_command(data)
    assert back["wfs"] == pytest.approx(6.25) and back["counter"] == 42 and back["bits"]["weld_start"]


@pytest.mark.parametrize("transport", TRANSPORTS)
async def test_reconnect_after_the_device_comes_back(transport):
    async with power_rig(transport, timeout_ms=150) as (th, sim, ps, _):
        ps.set_wire_feed(5.0)
        ps.set_weld_start(False)
        th.call(sim.inject, "silence", duration_s=0.4)
        with pytest.raises(LinkLost):
            for _ in range(100):
                await ps.next_status()
        with pytest.raises(LinkLost):
            ps.set_weld_start(True)           # no start on a dead link
        await asyncio.sleep(0.5)
        await ps.connect()
        st = await ps.next_status()
        assert st.watchdog_ok and not st.command.weld_start
        assert th.call(lambda: sim.cmd.wfs) == pytest.approx(5.0, abs=0.005)

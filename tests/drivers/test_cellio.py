"""Cell I/O driver against its simulator; the part's lumped thermal model; the E-stop interlock."""
from __future__ import annotations

import asyncio
import math
import time
from contextlib import asynccontextmanager

import pytest

from controller.defaults import SIM_REPLY_TIMEOUT_MS

from controller.runtime.arc_handshake import ArcHandshake, drop_start_on_unsafe
from drivers.cellio import SWITCHES, CellInputs, CellIO, decode_inputs
from drivers.errors import DeviceError, LinkLost
from wire.cellio_map import INPUTS
from sims.cellio_sim import CellIOSim, serve_modbus_tcp
from sims.clock import SimClock
from sims.faults import parse_fault_spec
from sims.thermal import LumpedThermal
from sims.thread import SimThread
from sims.world import World
from tests.power_fixtures import power_rig

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


@asynccontextmanager
async def cellio_rig(*, time_scale: float = 1.0, world: World | None = None, faults=None, thermal=None,
                     th: SimThread | None = None, timeout_ms: float = SIM_REPLY_TIMEOUT_MS):
    own = th is None
    th = th or SimThread()
    sim = CellIOSim(clock=SimClock(time_scale), world=world, faults=faults, thermal=thermal)
    url, close = th.run(serve_modbus_tcp(sim))
    io = CellIO(url, timeout_ms=timeout_ms)
    await io.connect()
    try:
        yield th, sim, io
    finally:
        await io.close()
        th.run(close())
        if own:
            th.stop()


async def test_inputs_coils_and_registers_follow_the_io_map():
    async with cellio_rig() as (th, sim, io):
        st = await io.next_inputs()
        assert st.safe_to_weld() and st.part_temperature_c == pytest.approx(20.0)
        assert st.gas_flow_l_min == 0.0
        io.set_gas_valve(True)
        io.set_beacon("amber")
        io.set_door_lock(True)
        for _ in range(3):
            st = await io.next_inputs()
        assert th.call(lambda: dict(sim.coils)) == {"gas_valve": True, "beacon_green": False, "beacon_amber": True,
                                                    "beacon_red": False, "door_lock": True}
        assert st.gas_flow_l_min == pytest.approx(15.0)
        th.call(sim.set_gas_pressure, False)
        th.call(sim.set_fume_extraction, False)
        for _ in range(2):
            st = await io.next_inputs()
        assert not st.gas_ok and not st.fume_ok and st.gas_flow_l_min == 0.0 and not io.inputs_safe()
        with pytest.raises(Exception, match="beacon colour"):
            io.set_beacon("blue")


async def test_door_opened_at_a_chosen_time_is_reported_in_the_cycle_it_is_read():
    async with cellio_rig() as (th, sim, io):
        changes = []
        io.on_change(lambda prev, new: changes.append((time.monotonic(), prev, new)))
        at = th.call(sim.clock.now) + 0.3
        th.call(sim.open_door, at=at)
        for _ in range(20):
            await io.next_inputs()
        assert not changes, "not before its time"
        await asyncio.sleep(0.3)
        st = await io.next_inputs()
        assert not st.door_closed and len(changes) == 1
        _, prev, new = changes[0]
        assert prev.door_closed and not new.door_closed and new.estop_released


async def test_fault_spec_schedules_door_and_estop():
    spec = parse_fault_spec("door_open@t=0.2s,door_open=0.3s,estop@t=0.4s")
    async with cellio_rig(faults=spec) as (th, sim, io):
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.8:
            await io.next_inputs()
        log = th.call(lambda: list(sim.log))
        assert [(e["input"], e["value"]) for e in log] == [("door_closed", False), ("estop_released", False),
                                                          ("door_closed", True)]
        assert log[0]["t_sim"] == pytest.approx(0.2, abs=0.1)
        assert log[2]["t_sim"] == pytest.approx(0.5, abs=0.1)
        assert not io.inputs.estop_released and io.inputs.door_closed


def test_lumped_thermal_matches_the_analytic_solution():
    th = LumpedThermal(ambient_c=20.0, heat_capacity_j_k=2000.0, tau_s=120.0)
    p = 0.8 * 20.0 * 130.0               # η·U·I
    for _ in range(600):                   # 60 s of arc in 0.1 s steps
        th.step(p, 0.1)
    t_inf = 20.0 + p * 120.0 / 2000.0
    expect = t_inf + (20.0 - t_inf) * math.exp(-60.0 / 120.0)
    assert th.temperature_c == pytest.approx(expect, rel=1e-9)
    hot = th.temperature_c
    assert hot == pytest.approx(69.105, abs=1e-3)
    wait = th.time_to_cool(40.0)          # the interpass wait down to 40 °C
    th.step(0.0, wait)
    assert th.temperature_c == pytest.approx(40.0, abs=1e-9)
    assert wait == pytest.approx(120.0 * math.log((hot - 20.0) / 20.0))
    assert th.time_to_cool(20.0) == math.inf


async def test_pyrometer_heats_while_the_arc_burns_and_cools_after():
    world = World(arc_efficiency=0.8)
    thermal = LumpedThermal(20.0, 2000.0, 120.0)
    async with cellio_rig(time_scale=100.0, world=world, thermal=thermal) as (th, sim, io):
        clock = sim.clock
        th.call(world.set_arc, True, 130.0, 20.0, clock.now())
        t_on = clock.now()
        await asyncio.sleep(0.6)             # ~60 s of process time
        th.call(world.set_arc, False, 0.0, 0.0, clock.now())
        t_arc = clock.now() - t_on
        st = await io.next_inputs()
        t_inf = 20.0 + 0.8 * 130.0 * 20.0 * 120.0 / 2000.0
        expect = t_inf + (20.0 - t_inf) * math.exp(-t_arc / 120.0)
        assert st.part_temperature_c == pytest.approx(expect, abs=3.0)
        assert st.part_temperature_c > 60.0
        peak = st.part_temperature_c
        await asyncio.sleep(0.6)             # cooling toward ambient
        st = await io.next_inputs()
        assert 20.0 < st.part_temperature_c < peak - 10.0


async def test_silent_coupler_is_a_lost_link_naming_the_url():
    async with cellio_rig(timeout_ms=100) as (th, sim, io):
        errors = []
        io.on_error(errors.append)
        th.call(sim.silence)
        with pytest.raises(LinkLost, match=r"cell I/O .*tcp://127\.0\.0\.1:\d+.*no reply within 100 ms"):
            for _ in range(50):
                await io.next_inputs()
        assert errors and not io.inputs_safe()


@pytest.mark.parametrize("action", ["press_estop", "open_door"])
async def test_estop_or_door_drops_the_weld_start_within_one_cycle(action):
    async with power_rig() as (th, psim, ps, world):
        async with cellio_rig(th=th, world=world) as (_, iosim, io):
            arc = ArcHandshake(ps)
            dropped = []
            drop_start_on_unsafe(io, ps, on_trip=lambda new: dropped.append(new.t))
            ps.set_wire_feed(6.0)
            await arc.start()
            th.call(getattr(iosim, action))
            await asyncio.wait_for(_until(lambda: dropped), 1.0)
            st = await ps.next_status()
            if st.command.weld_start:   # the one cycle already on the wire when the input tripped
                st = await ps.next_status()
            assert not st.command.weld_start
            assert st.t - dropped[0] <= 0.060             # the next power cycle carries it (strict: bench/)
            seen = th.call(lambda: [h for h in psim.history if h[0] >= dropped[0] - 1e-3])
            # at most the one cycle already on the wire still carries the start
            assert seen and not seen[-1][2]["weld_start"]
            assert not any(h[2]["weld_start"] for h in seen[1:])


async def _until(pred):
    while not pred():
        await asyncio.sleep(0.001)


def test_cycle_statistics_give_the_p99_period_from_a_bounded_histogram():
    # the benchmark compares the controller's p99 cycle period with and without OPC UA: 99 cycles
    # on time (10 ms) and one stalled (40 ms) make a p99 of 10 ms and a max of 40 ms
    from drivers.cyclic import CycleStats

    st = CycleStats()
    assert st.period_percentile_ms(99) is None
    for _ in range(99):
        st.add_period(0.010)
    st.add_period(0.040)
    assert st.period_percentile_ms(99) == 10.1 and st.period_percentile_ms(100) == 40.1
    st.add_period(5.0)   # beyond the histogram: counted in the last bin, never an index error
    assert st.period_percentile_ms(100) == 1000.1
    assert len(st.hist) == 10_001


# -- inputs by name (issue 25): the signal map, not the position, says which input is which ----------


def test_a_reordered_signal_map_still_reads_the_door_as_the_door():
    prev = CellInputs(t=0.0, part_temperature_c=80.0, gas_flow_l_min=12.0)
    bits = [True, False, True, True]            # input 0 closed, input 1 open
    as_shipped = decode_inputs(bits, 1.0, prev)
    assert INPUTS[:2] == ("door_closed", "estop_released")
    assert as_shipped.door_closed and not as_shipped.estop_released
    swapped = ("estop_released", "door_closed", "gas_ok", "fume_ok")   # a coupler wired the other way
    st = decode_inputs(bits, 1.0, prev, names=swapped)
    assert st.estop_released and not st.door_closed and st.gas_ok and st.fume_ok
    assert (st.t, st.part_temperature_c, st.gas_flow_l_min) == (1.0, 80.0, 12.0)   # registers kept
    reordered = tuple(reversed(INPUTS))
    st = decode_inputs(list(reversed([False, True, True, False])), 1.0, prev, names=reordered)
    assert (st.door_closed, st.estop_released, st.gas_ok, st.fume_ok) == (False, True, True, False)


def test_the_signal_map_names_every_input_of_cellinputs():
    assert set(INPUTS) == set(SWITCHES)
    with pytest.raises(DeviceError, match="no input named estop_released"):
        decode_inputs([True] * 4, 0.0, CellInputs(t=0.0), names=("door_closed", "e_stop", "gas_ok", "fume_ok"))
    with pytest.raises(DeviceError, match="3 discrete inputs read"):
        decode_inputs([True] * 3, 0.0, CellInputs(t=0.0))


async def test_opening_the_door_trips_door_closed_and_not_the_estop():
    async with cellio_rig() as (th, sim, io):
        st = await io.next_inputs()
        assert st.door_closed and st.estop_released and io.inputs_safe()
        th.call(sim.open_door)
        for _ in range(3):
            st = await io.next_inputs()
        assert not st.door_closed and st.estop_released and not io.inputs_safe()
        th.call(sim.close_door)
        th.call(sim.press_estop)
        for _ in range(3):
            st = await io.next_inputs()
        assert st.door_closed and not st.estop_released and not io.inputs_safe()

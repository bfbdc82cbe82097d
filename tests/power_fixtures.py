"""Shared set-up of the power-source tests: a simulator on its own thread, a driver per transport."""
from __future__ import annotations

from controller.defaults import SIM_REPLY_TIMEOUT_MS

import uuid
from contextlib import asynccontextmanager

from core.config import load_material
from core.realtime import elevate, is_realtime, relax
from drivers.power import PowerSource
from drivers.power_can import CanPowerSource
from drivers.power_modbus import ModbusPowerSource
from sims.clock import SimClock
from sims.power_sim import PowerSourceSim, serve_can, serve_modbus_rtu, serve_modbus_tcp
from sims.thread import SimThread
from sims.world import World

TRANSPORTS = ("modbus_tcp", "modbus_rtu", "can")
MATERIAL = load_material("inconel718-1.0mm")


@asynccontextmanager
async def power_rig(transport: str = "modbus_tcp", *, time_scale: float = 1.0, faults=None,
                    timeout_ms: float = SIM_REPLY_TIMEOUT_MS, connect: bool = True):
    """Yield (sim_thread, sim, driver, world); the sim runs on its own loop as a real device would.

    The driver's cycle runs on this test's loop at the controller's real-time priority, as
    `CellController.start` runs it (core/realtime.py): time-shared, beside another test worker's
    real-time cell it went unscheduled for over the simulator's 100 ms watchdog now and then, and
    the source dropped the start (error 50) in the middle of a 1.5 s ignition timeout.
    """
    rt = is_realtime()
    if not rt:
        elevate("power rig device cycles")
    th = SimThread()
    world = World()
    sim = PowerSourceSim(MATERIAL, clock=SimClock(time_scale), world=world, faults=faults, seed=1)
    ps: PowerSource
    if transport == "modbus_tcp":
        url, close = th.run(serve_modbus_tcp(sim))
        ps = ModbusPowerSource(url, MATERIAL, timeout_ms=timeout_ms)
    elif transport == "modbus_rtu":
        url, close = th.run(serve_modbus_rtu(sim))
        ps = ModbusPowerSource(url, MATERIAL, timeout_ms=timeout_ms)
    else:
        chan = f"ps-{uuid.uuid4().hex[:8]}"
        url, close = th.run(serve_can(sim, "virtual", chan))
        ps = CanPowerSource(interface="virtual", channel=chan, material=MATERIAL, timeout_ms=timeout_ms)
    try:
        if connect:
            await ps.connect()
        yield th, sim, ps, world
    finally:
        await ps.close()
        th.run(close())
        th.stop()
        if not rt:
            relax()


async def wait_for(ps: PowerSource, pred, timeout_s: float = 3.0):
    """Cycle until `pred(status)` holds; the status, or AssertionError after `timeout_s`."""
    import time
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        st = await ps.next_status()
        if pred(st):
            return st
    raise AssertionError(f"condition not met within {timeout_s} s; last status {st}")

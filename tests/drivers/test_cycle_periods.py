"""A build's cycle periods are its own (drivers/cyclic.py; docs/testing.md, "A loop that never blocks")."""
from __future__ import annotations

import asyncio
import time

from drivers.cellio import CellIO
from sims.cellio_sim import CellIOSim, serve_modbus_tcp
from sims.clock import SimClock
from sims.thread import SimThread


def _busy(cpu_s: float) -> None:
    """Compute on the loop for `cpu_s` of this thread's CPU time (longer on a loaded host)."""
    end = time.thread_time() + cpu_s
    while time.thread_time() < end:
        pass


async def test_what_the_loop_did_before_the_restart_is_not_the_builds_period() -> None:
    # the loop computes 60 ms (a test's open_job on it, before the build), then the build starts
    # its periods: the period in progress counts from the restart, not from its cycle's start
    th = SimThread()
    url, close = th.run(serve_modbus_tcp(CellIOSim(clock=SimClock(1.0))))
    io = CellIO(url)
    await io.connect()
    try:
        for _ in range(5):
            await io.next_inputs()
        _busy(0.060)
        io.restart_periods()
        for _ in range(10):
            await io.next_inputs()
        assert io.stats.max_own_period_s < 0.030, io.stats.max_own_period_s   # the late-loop check's bound
        # and a stall after the restart is the build's
        _busy(0.060)
        for _ in range(3):
            await io.next_inputs()
        st = io.stats
        assert st.max_period_s >= 0.060 and st.max_own_period_s >= 0.050, (st.max_own_period_s, st.os_delay_at_max_s)
    finally:
        await io.close()
        th.run(close())
        th.stop()
        await asyncio.sleep(0)

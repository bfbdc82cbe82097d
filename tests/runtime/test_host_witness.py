"""The host witness (controller/runtime/host_witness.py): a CPU of this host that stops running is seen,
and a device whose answers wait while it was stopped is not a lost link; a device silent on a
host that runs is lost after `lost_after_cycles` cycles as before.

A CPU that stops running is played by stopping its witness (SIGSTOP): to the witness it is the
same thing, its wake comes late by the length of the stop.
"""
from __future__ import annotations

import asyncio
import os
import signal
import time

import pytest

from controller.runtime.host_witness import HostWitness
from drivers.cellio import CellIO
from drivers.errors import LinkLost
from sims.cellio_sim import CellIOSim, serve_modbus_tcp
from sims.clock import SimClock
from sims.thread import SimThread

pytestmark = pytest.mark.realtime  # a device cycle and a stopped CPU on the wall clock (tests/conftest.py)


@pytest.fixture
def witness():
    w = HostWitness()
    line = w.start()
    if not w.running:
        pytest.skip(line)   # no real-time priority here (not root): the witness refuses to run
    yield w
    w.close()


def _stop_cpu(w: HostWitness, seconds: float) -> tuple[float, float]:
    os.kill(w.pids[0], signal.SIGSTOP)
    t0 = time.monotonic()
    time.sleep(seconds)
    os.kill(w.pids[0], signal.SIGCONT)
    return t0, time.monotonic()


def test_a_cpu_that_stopped_running_is_seen_for_as_long_as_it_stopped(witness):
    time.sleep(0.05)
    before = witness.stalled_s(time.monotonic() - 0.04, time.monotonic())
    os.kill(witness.pids[0], signal.SIGSTOP)
    t0 = time.monotonic()
    time.sleep(0.08)
    during = witness.stalled_s(t0, time.monotonic())      # still stopped: seen before it wakes
    os.kill(witness.pids[0], signal.SIGCONT)
    t1 = time.monotonic()
    time.sleep(0.02)
    after = witness.stalled_s(t0 - 0.01, t1 + 0.01)
    assert before < 0.015                   # a running host: at most the VM's few-ms hiccups
    assert during > 0.05
    assert after == pytest.approx(t1 - t0, abs=0.015)
    assert witness.stalled_s(t1 + 0.015, time.monotonic()) < 0.015   # and it is over


async def _read_for(io: CellIO, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        await io.next_inputs()


@pytest.mark.parametrize("cpu_stopped", [True, False])
async def test_a_device_silent_while_a_cpu_stopped_is_not_lost(witness, cpu_stopped):
    th = SimThread()
    sim = CellIOSim(clock=SimClock(1.0))
    url, close = th.run(serve_modbus_tcp(sim))
    io = CellIO(url, lost_after_cycles=3)          # 30 ms budget, as docs/contract.md §5's default
    io.host_stalled_s = witness.stalled_s
    await io.connect()
    try:
        await _read_for(io, 0.1)
        if cpu_stopped:
            # the device's process does not run for 150 ms (its requests wait in the socket and
            # are answered late), nor does a CPU of the host: a virtual CPU taken away
            th.loop.call_soon_threadsafe(time.sleep, 0.15)
            await asyncio.to_thread(_stop_cpu, witness, 0.17)
            await _read_for(io, 0.2)               # the replies come back: nothing lost
            assert io.error is None and io.stats.lost == 0
            assert io.stats.host_stalls >= 5      # the cycles were not counted against the device
        else:
            th.call(sim.silence, 0.15)             # the device does not answer, the host runs
            with pytest.raises(LinkLost, match="no reply within 30 ms"):
                await _read_for(io, 0.3)
    finally:
        await io.close()
        th.run(close())
        th.stop()

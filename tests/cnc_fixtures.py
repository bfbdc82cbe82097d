"""Shared set-up of the CNC tests: a CNC simulator served over a serial link, a grbl driver on it."""
from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from drivers.grbl import CncLink
from sims.cnc import CncSim
from sims.faults import parse_fault_spec
from sims.transport import SerialServer


@asynccontextmanager
async def cnc_link(sim: CncSim, *, rx_buffer_bytes: int = 128) -> AsyncIterator[CncLink]:
    """`sim` started and served at 115,200 baud on a free local port, with no seeded fault; yields
    a grbl driver on it, not yet connected (`rx_buffer_bytes`: what cell.yaml declares; grbl 1.1h's 128 by default).
    Closes the driver, the server and the simulator on the way out."""
    sim.start()
    server = SerialServer(sim, name="cnc", spec=parse_fault_spec(""), baud=115200)
    link = CncLink(await server.start(None, ephemeral=True), rx_buffer_bytes=rx_buffer_bytes)
    try:
        yield link
    finally:
        await link.close()
        await server.close()
        await sim.close()

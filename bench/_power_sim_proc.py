"""A power-source simulator in its own process (a separate device): prints its URL, serves until stdin closes.

python -m bench._power_sim_proc modbus_tcp|modbus_rtu|can [CAN group] [CAN port]
"""
from __future__ import annotations

import asyncio
import sys

from core.config import load_material
from sims.clock import SimClock
from sims.power_sim import PowerSourceSim, serve_can, serve_modbus_rtu, serve_modbus_tcp
from sims.world import World


async def amain(transport: str, channel: str, port: int) -> None:
    sim = PowerSourceSim(load_material("inconel718-1.0mm"), clock=SimClock(60.0), world=World())
    if transport == "modbus_tcp":
        url, close = await serve_modbus_tcp(sim)
    elif transport == "modbus_rtu":
        url, close = await serve_modbus_rtu(sim)
    else:
        url, close = await serve_can(sim, "udp_multicast", channel, port=port)
    print(url, flush=True)
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, sys.stdin.read)   # until the parent closes our stdin
    await close()


if __name__ == "__main__":
    asyncio.run(amain(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "239.74.163.9",
                      int(sys.argv[3]) if len(sys.argv) > 3 else 43199))

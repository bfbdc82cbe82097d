"""`cell sim up`: every simulator in one process on one asyncio loop, coupled through a World.

Each simulator module listed in SIM_MODULES provides `async def serve(ctx: SimContext) ->
list[Served]`: it starts its server(s) on the URL(s) of cell.yaml (or on ephemeral loopback
ports when `ctx.ephemeral`), and returns what it serves. A module not built yet is skipped.
"""
from __future__ import annotations

import asyncio
import importlib
import os
import signal
import sys
from typing import Callable

from core.realtime import SIM_RT_PRIORITY, elevate, quiet_gc
from core.runtime_dir import runtime_dir
from sims.clock_server import ClockServer
from sims.inject import inject
from sims.context import Served, SimContext

__all__ = ["SIM_MODULES", "SimContext", "Served", "serve_all", "close_all", "run_forever"]

SIM_MODULES = ["sims.robot_sim", "sims.cnc", "sims.power_sim", "sims.cellio_sim"]


async def serve_all(ctx: SimContext, modules: list[str] | None = None) -> list[Served]:
    served: list[Served] = []
    try:
        for name in modules or SIM_MODULES:
            mod = importlib.import_module(name)  # a missing simulator is an error naming it
            served.extend(await mod.serve(ctx))
    except BaseException:
        await close_all(served)  # e.g. a port in use: free what was already started
        raise
    return served


async def close_all(served: list[Served]) -> None:
    for s in reversed(served):
        try:
            await s.close()
        except Exception:  # closing must go on for the others
            pass


async def run_forever(ctx: SimContext, on_ready: Callable[[list[Served]], None]) -> None:
    """Serve until SIGINT (Ctrl-C) or SIGTERM, then close every server and flush the logs."""
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):  # not the main thread: Ctrl-C still cancels
            pass
    served: list[Served] = []
    clock = ClockServer(ctx.clock, ctx.cell.devices.cnc.url, runtime_dir(),
                        lambda req: inject({x.device: x.sim for x in served}, req.device, req.fault, req.duration_s))
    # Before the servers start; every simulator runs on this thread's loop.
    rt = elevate("simulators", SIM_RT_PRIORITY)
    if "cannot" in rt:  # the clear line the operator needs; nothing when it worked
        sys.stderr.write(f"cell sim up: {rt}\n")
    slow_ms = os.environ.get("CELL_SLOW_CALLBACK_MS")  # diagnosis: log loop stalls longer than this
    if slow_ms:
        loop.set_debug(True)
        loop.slow_callback_duration = float(slow_ms) / 1000.0
    try:
        served = await serve_all(ctx)
        await clock.start()   # a command lowers the time scale to what it can feed (docs/controller.md)
        quiet_gc(collect=True)  # full collections of this heap stalled replies 58-84 ms
        on_ready(served)
        await stop.wait()
    finally:
        await clock.close()
        await close_all(served)
        ctx.world.close()

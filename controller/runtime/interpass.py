"""The interpass rule before a layer's first arc (docs/contract.md §3 item 4): the pyrometer below the
layer's limit, or, without a reading, the layer's dwell."""
from __future__ import annotations

import asyncio
import time
from typing import Callable

from controller.journal.store import Journal
from controller.runtime.events import EventBus
from core.errors import CellError


class InterpassError(CellError):
    """The part does not cool below the interpass limit within the timeout (a build error)."""


async def interpass_wait(layer: int, limit: float, dwell: float, timeout_s: float, scale: float,
                         temperature: Callable[[], float | None], journal: Journal, bus: EventBus) -> None:
    """Wait before layer `layer`'s first arc: below `limit` °C (the pyrometer), else `dwell`
    process seconds (none before layer 0); InterpassError after `timeout_s` process seconds above."""
    t0 = time.monotonic()
    temp = temperature()
    if temp is None:
        if layer == 0:
            return
        dwell_wall = dwell / scale
        journal.event("info", f"interpass dwell {dwell:.0f} s (no pyrometer)", layer=layer)
        while (left := dwell_wall - (time.monotonic() - t0)) > 0:
            bus.update(interpass_remaining_s=left * scale)
            await asyncio.sleep(min(left, 0.1))
        bus.update(interpass_remaining_s=None)
        return
    bus.update(interpass_limit_c=limit, temperature_c=temp)
    if temp < limit:
        return
    journal.event("info", f"interpass wait: part at {temp:.0f} °C, limit {limit:.0f} °C", layer=layer)
    while (temp := temperature()) is not None and temp >= limit:
        if (time.monotonic() - t0) * scale > timeout_s:
            raise InterpassError(f"interpass: the part stays above {limit:.0f} °C ({temp:.0f} °C); check the pyrometer")
        bus.update(temperature_c=temp)
        await asyncio.sleep(0.02)

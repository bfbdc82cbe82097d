"""Waiting for a driver's state to reach a condition: every change wakes every waiter, which
checks its own predicate again (no polling, no lost wake-ups on one event loop)."""
from __future__ import annotations

import asyncio
import time
from typing import Callable

from drivers.errors import DeviceTimeout


class Changes:
    """`notify()` after a state change; `await until(pred, ...)` returns once `pred()` holds."""

    def __init__(self, where: str) -> None:
        self.where = where                 # "robot at URL": named in the timeout's message
        self._event = asyncio.Event()

    def notify(self) -> None:
        ev, self._event = self._event, asyncio.Event()
        ev.set()

    async def until(self, pred: Callable[[], bool], timeout: float | None, what: str,
                    check: Callable[[], None] | None = None) -> None:
        """Wait until `pred()`; `check()` (raising, e.g. LinkLost) before every wait;
        DeviceTimeout naming `what` after `timeout` seconds (None: no limit)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not pred():
            if check is not None:
                check()
            ev = self._event
            if deadline is None:
                await ev.wait()
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                raise DeviceTimeout(f"{self.where}: timed out waiting for {what}")
            try:
                await asyncio.wait_for(ev.wait(), left)
            except asyncio.TimeoutError:
                raise DeviceTimeout(f"{self.where}: timed out waiting for {what}") from None

"""Run simulators on their own asyncio loop in a background thread (tests, benchmarks).

A device is a separate machine: its timing must not stall when the controller's loop does
(e.g. to prove the power source's watchdog drops the start when the host stops cycling).
"""
from __future__ import annotations

import asyncio
import threading
from typing import Any, Callable, Coroutine

from core.realtime import SIM_RT_PRIORITY, elevate
from sims.loop import precise_loop


class SimThread:
    """An event loop in a daemon thread; `run(coro)` / `call(fn)` execute on it and wait."""

    def __init__(self) -> None:
        self.loop = precise_loop()
        self._thread = threading.Thread(target=self._serve, name="sim loop", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        # a device keeps its own time: real-time priority when allowed (as `cell sim up`), so that
        # CPU load beside an in-process build (--sim, the TUI, tests) does not stall it
        elevate("in-process simulators", SIM_RT_PRIORITY)
        self.loop.run_forever()

    def run(self, coro: Coroutine[Any, Any, Any], timeout: float = 10.0) -> Any:
        """Run a coroutine on the sim loop and return its result."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def call(self, fn: Callable[..., Any], *args: Any, **kw: Any) -> Any:
        """Call `fn` on the sim loop (thread-safe access to a simulator) and return its result."""
        async def _do() -> Any:
            return fn(*args, **kw)
        return self.run(_do())

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5.0)
        self.loop.close()

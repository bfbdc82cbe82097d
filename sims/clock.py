"""Simulated process time shared by the simulators and the controller (docs/contract.md §6)."""
from __future__ import annotations

import time
from typing import Callable


class SimClock:
    """Process time that runs `time_scale` times faster than wall time.

    Scaled: motion execution, gas flows, ignition and burn-back, thermal behaviour, dwells.
    Never scaled: link timing (heartbeats, the 10 ms bus cycle, watchdogs, link-loss timeouts).
    """

    def __init__(self, time_scale: float = 1.0) -> None:
        if time_scale <= 0:
            raise ValueError("time_scale must be positive")
        # (process time at the anchor, monotonic time of the anchor, scale): one tuple, replaced
        # whole, so a reader on another thread never mixes an old anchor with a new scale
        self._anchor = (0.0, time.monotonic(), float(time_scale))
        self._watchers: list[Callable[[float], None]] = []

    def watch(self, fn: Callable[[float], None]) -> None:
        """Call `fn(new scale)` whenever the scale changes (the serial lines keep their rate in
        simulated time)."""
        self._watchers.append(fn)

    @property
    def time_scale(self) -> float:
        return self._anchor[2]

    def set_scale(self, time_scale: float) -> None:
        """Run at `time_scale` from now on; process time goes on without a jump (a repair's probing
        at the cell's time scale, its build at what the CNC link can feed: controller/harness/repair.py)."""
        if time_scale <= 0:
            raise ValueError("time_scale must be positive")
        now = time.monotonic()
        base, t0, k = self._anchor
        self._anchor = (base + (now - t0) * k, now, float(time_scale))
        for fn in list(self._watchers):
            fn(float(time_scale))

    def now(self) -> float:
        """Simulated seconds since the clock started."""
        base, t0, k = self._anchor
        return base + (time.monotonic() - t0) * k

    def wall(self, sim_seconds: float) -> float:
        """Wall-clock seconds that `sim_seconds` of process time take."""
        return sim_seconds / self._anchor[2]

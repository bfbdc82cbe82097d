"""Simulated process time shared by the simulators and the controller (DESIGN.md §6)."""
from __future__ import annotations

import time


class SimClock:
    """Process time that runs `time_scale` times faster than wall time.

    Scaled: motion execution, gas flows, ignition and burn-back, thermal behaviour, dwells.
    Never scaled: link timing (heartbeats, the 10 ms bus cycle, watchdogs, link-loss timeouts).
    """

    def __init__(self, time_scale: float = 1.0) -> None:
        if time_scale <= 0:
            raise ValueError("time_scale must be positive")
        self.time_scale = float(time_scale)
        self._t0 = time.monotonic()

    def now(self) -> float:
        """Simulated seconds since the clock started."""
        return (time.monotonic() - self._t0) * self.time_scale

    def wall(self, sim_seconds: float) -> float:
        """Wall-clock seconds that `sim_seconds` of process time take."""
        return sim_seconds / self.time_scale

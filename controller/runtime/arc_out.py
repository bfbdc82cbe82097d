"""Where the arc of a bead really went out when the controller died with the arc on.

After a SIGKILL the robot keeps executing its queue (it holds only after 3 s of silence) and the
power source keeps the arc until its watchdog drops the start (`watchdog_s` of wall time without a
new counter; then the simulator goes idle at once, another source may burn back first), so the deposit runs on past the last weld move journaled as
executed. `arc_out_lower_bound` estimates that stretch from device properties (`RunOn`, from
cell.yaml's `devices.power_source`), the time scale of the killed run and the pass's speed, and
caps it at the position the robot reports after the reconnect (the torch deposits nothing beyond
where it went). It is a lower bound, so a resumed bead never leaves a gap; the re-arc overlap is
at most one weld move plus the timing slack at the weld speed. Pure functions, no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from core.config import PowerSourceDevice

Point = tuple[float, float, float]


@dataclass(frozen=True)
class RunOn:
    """How long the arc burns on after the controller dies (device properties, cell.yaml
    `devices.power_source`), and the slack taken off that estimate."""

    watchdog_s: float = 0.100        # weld start dropped after this long without a new counter (wall)
    # the arc after the watchdog dropped the start: the simulator latches the fault and goes idle
    # at once (no burn-back, sims/power_sim.py `_latch`); a source that burns back sets this
    burnback_s: float = 0.0          # process seconds
    burnback_min_wall_s: float = 0.020  # a scaled burn-back never lasts less (2 bus cycles)
    # the last counter may have reached the device up to two bus cycles before the last journaled
    # EXE was handled, and the simulators act on 2-5 ms ticks: taken off the run-on time
    timing_slack_s: float = 0.020
    margin_mm: float = 0.1           # taken off the estimated arc-out point (position rounding)

    @classmethod
    def from_device(cls, dev: PowerSourceDevice, **kw: float) -> "RunOn":
        """From cell.yaml's `devices.power_source` (watchdog_ms, watchdog_burnback_s)."""
        return cls(watchdog_s=dev.watchdog_ms / 1000.0, burnback_s=dev.watchdog_burnback_s, **kw)

    def wall_s(self, time_scale: float) -> float:
        """Wall seconds the torch surely moved with the arc on after the last journaled EXE."""
        burn = max(self.burnback_s / time_scale, self.burnback_min_wall_s) if self.burnback_s > 0 else 0.0
        return max(0.0, self.watchdog_s + burn - self.timing_slack_s)


# -- geometry along a pass (pure) -------------------------------------------------------------


def arc_lengths(pts: Sequence[Point]) -> list[float]:
    """Cumulative length along the polyline at each point (0 at the first)."""
    out = [0.0]
    for a, b in zip(pts, pts[1:]):
        out.append(out[-1] + math.dist(a, b))
    return out


def point_at(pts: Sequence[Point], cum: Sequence[float], s: float) -> tuple[int, Point]:
    """(k, P): P lies at length `s` on the polyline, on the move from pts[k] to pts[k + 1]."""
    s = min(max(s, 0.0), cum[-1])
    k = 0
    while k + 2 < len(cum) and cum[k + 1] <= s:
        k += 1
    seg = cum[k + 1] - cum[k]
    f = 0.0 if seg <= 0 else min(1.0, (s - cum[k]) / seg)
    if f <= 1e-9:
        return k, tuple(pts[k])  # type: ignore[return-value]
    a, b = pts[k], pts[k + 1]
    return k, (a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f)


def project(pts: Sequence[Point], cum: Sequence[float], pos: Sequence[float], from_s: float,
            tol_mm: float = 0.05) -> float | None:
    """Length along the polyline of `pos`, searching forward from `from_s`; None if off the path.

    The first match is taken, so on a path that comes back near itself the answer is the
    smaller length (the conservative one for an upper bound of the deposit).
    """
    k0, _ = point_at(pts, cum, from_s)
    for k in range(k0, len(pts) - 1):
        a, b = pts[k], pts[k + 1]
        d = [bi - ai for ai, bi in zip(a, b)]
        L2 = sum(v * v for v in d)
        if L2 <= 1e-18:
            continue
        t = max(0.0, min(1.0, sum((p - ai) * v for p, ai, v in zip(pos, a, d)) / L2))
        q = [ai + t * v for ai, v in zip(a, d)]
        if math.dist(q, pos) <= tol_mm:
            s = cum[k] + t * math.sqrt(L2)
            if s >= from_s - tol_mm:
                return max(s, from_s)
    return None


def arc_out_lower_bound(s_known: float, speed_mm_min: float, time_scale: float, run_on: RunOn,
                        s_robot: float | None, s_end: float) -> float:
    """Where to re-arc a bead whose controller died with the arc on (length along the pass).

    `s_known`: the deposit surely reached this far (last journaled EXE with the arc stable, or the
    re-arc point); `s_robot`: where the robot stopped after the crash (None: unknown, then no
    estimate is made). The torch moved at `speed_mm_min` of process time (time scale × wall) for at
    least `run_on.wall_s()` wall seconds with the arc on after `s_known`, unless the robot stopped
    first (its queue ran out): the arc went out at or after the smaller of the two.
    """
    if s_robot is None:
        return s_known
    run = speed_mm_min / 60.0 * time_scale * run_on.wall_s(time_scale)
    # the robot's position comes rounded to 1 µm (STA frames carry 3 decimals)
    est = min(s_known + run - run_on.margin_mm, s_robot - 0.001)
    if est >= s_end - 0.001:
        return s_end  # the torch reached the end of the bead with the arc still on
    return max(s_known, est)

"""Link liveness, shared by the serial device links (docs/contract.md §5, "Link health").

A link is *heard* when a valid reply that fits what the host sent arrives; what is only
well-formed (a heartbeat, a duplicate) or not even that (a bad checksum, garbage, a flood) is
never heard. The link is *lost* after `lost_after_s` without being heard (the robot: 3 s);
a reply heard after more than `late_after_s` of silence is *late*: counted in the statistics,
never a fault. A run of bad frames with no valid one between is the driver's to judge (a
garbling device).

`LinkLiveness` keeps that accounting and nothing of a protocol: a driver subclasses it, calls
`_link_up()` when it (re)connects, `_valid()` for every frame that decodes, `_bad()` for every
one that does not, `_heard()` for the valid frames that prove the device is alive, and asks
`_lost_due()` / `_quiet()` from its timer. `drivers.robot.RobotLink` (RLP/1) is the first user;
a second robot protocol or the grbl link reuses it as is (`_allow_silence_until()` covers a
command such as grbl's `$H` during which the device legitimately says nothing).
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

RTT_SAMPLES = 2000   # round trips kept for the statistics (mean, p99)


@dataclass
class LinkHealth:
    """The link statistics every device link keeps: the views, the report and the benchmark read them."""

    heard: int = 0       # valid replies that fit what was sent (they refresh liveness)
    late: int = 0        # of those, heard after more than `late_after_s` of silence (not a fault)
    bad: int = 0         # frames received but not valid (checksum, syntax, over the per-read bound)
    lost: int = 0        # times the link was declared lost (silence, closed port)
    rtt_s: deque[float] = field(default_factory=lambda: deque(maxlen=RTT_SAMPLES))

    @property
    def rtt_ms_mean(self) -> float:
        return 1000.0 * sum(self.rtt_s) / len(self.rtt_s) if self.rtt_s else float("nan")

    @property
    def rtt_ms_p99(self) -> float:
        if not self.rtt_s:
            return float("nan")
        s = sorted(self.rtt_s)
        return 1000.0 * s[min(len(s) - 1, int(0.99 * len(s)))]

    def as_dict(self) -> dict[str, float | int | dict[str, int]]:
        return {"heard": self.heard, "late": self.late, "bad": self.bad, "lost": self.lost,
                "rtt_ms_mean": round(self.rtt_ms_mean, 3), "rtt_ms_p99": round(self.rtt_ms_p99, 3)}


H = TypeVar("H", bound=LinkHealth)


class LinkLiveness(Generic[H]):
    """Heard / late / lost accounting of one link; `H` is the driver's statistics (a LinkHealth)."""

    def __init__(self, stats: H, *, lost_after_s: float, late_after_s: float) -> None:
        if not 0.0 < late_after_s <= lost_after_s:
            raise ValueError(f"need 0 < late_after_s ({late_after_s}) <= lost_after_s ({lost_after_s})")
        self.stats = stats
        self.lost_after_s = lost_after_s
        self.late_after_s = late_after_s
        self._last_heard = 0.0
        self._bad_run = 0
        self._silence_ok_until = 0.0

    def _link_up(self, now: float | None = None) -> None:
        """The link is (re)connected: silence is counted from now."""
        self._last_heard = time.monotonic() if now is None else now
        self._bad_run = 0
        self._silence_ok_until = 0.0

    def _valid(self) -> None:
        """A frame decoded: the run of bad frames ends (it is not necessarily heard)."""
        self._bad_run = 0

    def _bad(self) -> int:
        """A frame that is not valid: counted; returns the run of bad frames so far."""
        self.stats.bad += 1
        self._bad_run += 1
        return self._bad_run

    def _heard(self, now: float | None = None) -> bool:
        """A valid reply that fits what was sent: the link is alive. True when it came late."""
        now = time.monotonic() if now is None else now
        late = now - self._last_heard > self.late_after_s
        self.stats.heard += 1
        if late:
            self.stats.late += 1
        self._last_heard = now
        return late

    def _allow_silence_until(self, t: float) -> None:
        """The device may be silent until monotonic time `t` (e.g. a command that answers only when done)."""
        self._silence_ok_until = max(self._silence_ok_until, t)

    def silent_s(self, now: float | None = None) -> float:
        """Seconds since the link was last heard (or came up)."""
        return (time.monotonic() if now is None else now) - self._last_heard

    def _quiet(self, now: float) -> bool:
        """Not heard for `late_after_s`: what is heard next is late; a driver may hold motion now."""
        return self.silent_s(now) >= self.late_after_s

    def _lost_due(self, now: float, margin_s: float = 0.0) -> bool:
        """Not heard for `lost_after_s` (less `margin_s`, a timer's period) outside an allowed silence."""
        return now >= self._silence_ok_until and self.silent_s(now) >= self.lost_after_s - margin_s

    def _count_lost(self) -> None:
        self.stats.lost += 1

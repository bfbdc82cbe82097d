"""Bookkeeping of the grbl driver: lines awaiting their answer and the spans of status reports
the acknowledgement watchdog judges (`state.py` and `receive.py` use them)."""
from __future__ import annotations

import asyncio
import re
import time
from dataclasses import dataclass, field

from wire.grbl_protocol import Alarm, Error, Ok

Answer = Ok | Error


@dataclass
class Pending:
    """One line sent and not yet answered (`ok` / `error:N`), with what grbl printed meanwhile."""

    line: str
    nbytes: int
    future: asyncio.Future[Answer]
    number: int | None = None           # 1-based line number in a stream
    lines: list[str] = field(default_factory=list)
    alarm: Alarm | None = None
    sent_at: float = field(default_factory=time.monotonic)


class ReportSpan:
    """Receipt times of one kind of status report: the first since our last line or 'ok'
    (`since`), and the newest (`seen`). Its length is judged on what grbl said, never on the
    clock alone."""

    def __init__(self) -> None:
        self.since: float | None = None
        self.seen = 0.0

    def see(self, now: float, last_activity: float) -> None:
        self.seen = now
        if self.since is None or self.since <= last_activity:
            self.since = now

    def clear(self) -> None:
        self.since = None

    def length(self, last_activity: float) -> float | None:
        """Seconds between the first and the newest report since `last_activity`; None if none."""
        if self.since is None or self.since <= last_activity:
            return None
        return self.seen - self.since


def dwell_s(line: str) -> float:
    """Seconds a `G4 P…` line may legitimately keep grbl busy while Idle (0 for other lines)."""
    u = line.upper().replace(" ", "")
    if "G4" not in u or "P" not in u:
        return 0.0
    m = re.match(r"[-+]?[\d.]+", u.split("P", 1)[1])
    if m is None:
        return 0.0
    try:
        return float(m.group(0))
    except ValueError:
        return 0.0

"""What the robot link believes (issue 13): liveness from valid, expected frames only, and the
protocol faults of a robot that lies.

- Heard: a valid ACK / NAK / EXE / STA / MRK / ERR frame that fits what the host sent. A
  heartbeat proves nothing the keepalive's STA does not (it cannot tell a robot that executes
  from one stuck in a loop), so HB never refreshes liveness; bad CRCs and bad syntax never do.
- Flood: more than HB_FLOOD_PER_S heartbeats within one second (nominal: 1/s) is a misbehaving
  robot: a protocol fault.
- Lies: an ACK or EXE of a ticket never transmitted, an EXE beyond the ACKed tickets while no
  frame was lost on the way (a lost ACK makes the next EXE an implicit ACK), or an EXE going
  backwards: a protocol fault.
- Garble: GARBLED_RUN bad frames in a row is a protocol fault at once (line noise at 1 % of
  bytes makes that ~1e-8 per frame); a robot quiet for SUSPECT_S with moves outstanding is held
  (`!HOLD`, released by `!GO` when it speaks again) so it does not go on depositing unseen.
- Reading is bounded per read: the build's own frames (ACK, NAK, EXE, STA, MRK, ERR) first, at
  most MAX_OWN_PER_READ of them; heartbeats after, at most MAX_HB_PER_READ decoded (the rest
  are only counted), so a flood cannot starve the event loop.
"""
from __future__ import annotations

import time
from collections import deque

GARBLED_RUN = 10          # this many bad frames in a row (none valid between): a garbling robot
SUSPECT_S = 0.75          # no valid frame for this long with moves outstanding: !HOLD (lost at 3 s)
HB_FLOOD_PER_S = 20        # heartbeats in any 1 s window above this: a flood
MAX_OWN_PER_READ = 512
MAX_HB_PER_READ = 4


def split_lines(lines: list[bytes]) -> tuple[list[bytes], list[bytes]]:
    """(own frames first, heartbeats), by their first bytes (CRC checked later, on decode)."""
    own: list[bytes] = []
    hb: list[bytes] = []
    for ln in lines:
        (hb if ln.startswith(b"HB ") else own).append(ln)
    return own, hb


class FloodMeter:
    """Counts heartbeat-looking lines over a sliding one-second window."""

    def __init__(self, limit: int = HB_FLOOD_PER_S) -> None:
        self.limit = limit
        self._times: deque[tuple[float, int]] = deque()
        self._n = 0
        self.total = 0

    def add(self, n: int, now: float | None = None) -> bool:
        """Add `n` heartbeats seen now; True when the last second holds more than the limit."""
        if n <= 0:
            return False
        now = time.monotonic() if now is None else now
        self._times.append((now, n))
        self._n += n
        self.total += n
        while self._times and now - self._times[0][0] > 1.0:
            self._n -= self._times.popleft()[1]
        return self._n > self.limit

    @property
    def rate(self) -> int:
        return self._n

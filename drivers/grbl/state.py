"""The state the grbl driver's parts share (docs/architecture.md, "Packages, not friends").

`LinkState` is one explicit object: the receiving half (`receive.py`) fills it from what grbl
prints, the link (`link.py`) sends through it, and a stream (`stream.py`) or a safe stop
(`stop.py`) read and change it through its public fields and methods. No part reads another
part's private attributes.

Flow control is character counting: `in_flight` is the sum of `len(line) + 1` over the lines in
`pending` (sent, not yet answered), kept at most `capacity`, grbl's RX ring less one byte."""
from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass, field

from core.errors import InputError
from drivers.errors import LinkLost
from drivers.grbl.results import SafeStopResult
from drivers.grbl.status import Pending
from drivers.serial_async import SerialPort
from wire.grbl_protocol import Alarm, GrblStatus

__all__ = ["LinkState"]


@dataclass
class LinkState:
    """One grbl link's shared bookkeeping: the port, the lines in flight, the events tasks wait on."""

    url: str
    capacity: int                  # usable bytes of grbl's RX ring (its size less one)
    port: SerialPort               # replaced by every connect()
    pending: deque[Pending] = field(default_factory=deque)   # sent, not yet answered, in order
    in_flight: int = 0             # bytes of `pending`
    # the time-weighted in-flight bytes of the current stream
    fill_area: float = 0.0
    fill_t: float = field(default_factory=time.monotonic)
    fill_max: int = 0
    stream_error: Pending | None = None   # the first streamed line refused with error:N
    stream_alarm: Alarm | None = None     # an ALARM:N raised while lines were pending
    stop_gen: int = 0              # bumped by every safe_stop(): streams stop sending
    stop_task: asyncio.Task[SafeStopResult] | None = None
    lost: LinkLost | None = None
    closing: bool = False          # close() in progress: a read error is not a lost link
    tasks: list[asyncio.Task[None]] = field(default_factory=list)   # reader and poller: connected
    status_waiters: list[asyncio.Future[GrblStatus]] = field(default_factory=list)
    banner: asyncio.Event = field(default_factory=asyncio.Event)    # set by each banner (reset)
    changed: asyncio.Event = field(default_factory=asyncio.Event)   # replaced by each pulse()
    buf: bytearray = field(default_factory=bytearray)               # received bytes without a line end yet
    homed: bool = False
    last_q: float = 0.0            # when `?` was last sent, monotonic
    last_sent: float = 0.0         # when the last line was sent, monotonic
    last_rx: float = field(default_factory=time.monotonic)   # when a byte last arrived (or the alarm grace ends)
    quiet_until: float = 0.0       # grbl answers nothing during $H: no link/ack watchdog until then
    send_lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    @property
    def stopping(self) -> bool:
        """A safe stop is in progress: no line is sent meanwhile."""
        return self.stop_task is not None and not self.stop_task.done()

    def pulse(self) -> None:
        """Wake every task waiting in `wait_changed()`."""
        ev, self.changed = self.changed, asyncio.Event()
        ev.set()

    async def wait_changed(self) -> None:
        await self.changed.wait()

    def set_in_flight(self, n: int) -> None:
        now = time.monotonic()
        self.fill_area += self.in_flight * (now - self.fill_t)
        self.fill_t = now
        self.in_flight = max(n, 0)
        self.fill_max = max(self.fill_max, self.in_flight)

    def fail_pending(self, exc: Exception) -> None:
        """Every line still unanswered fails with `exc` (a reset flushed it, the link was lost)."""
        pend, self.pending = self.pending, deque()
        self.set_in_flight(0)
        for p in pend:
            if not p.future.done():
                p.future.set_exception(exc)
                p.future.exception()  # mark retrieved: nobody may be awaiting a stream's lines
        self.pulse()

    def check_lost(self) -> None:
        if self.lost is not None:
            raise LinkLost(str(self.lost))
        if not self.tasks:
            raise LinkLost(f"cnc at {self.url}: not connected (call connect() first)")

    async def write(self, data: bytes) -> None:
        if self.lost is not None:
            raise LinkLost(str(self.lost))
        await self.port.write(data)

    async def send_line(self, line: str, number: int | None = None) -> Pending:
        data = line.encode("ascii") + b"\n"
        p = Pending(line, len(data), asyncio.get_running_loop().create_future(), number)
        self.pending.append(p)
        self.last_sent = p.sent_at
        self.set_in_flight(self.in_flight + p.nbytes)
        await self.write(data)
        return p

    def check_line(self, line: str, number: int | None = None) -> str:
        if "\n" in line or "\r" in line:
            raise InputError(f"cnc: one line at a time, got {line!r}")
        try:
            line.encode("ascii")
        except UnicodeEncodeError:
            raise InputError(f"cnc: {'line ' + str(number) + ' ' if number else ''}{line!r} is not ASCII") from None
        if len(line) + 1 > self.capacity:
            raise InputError(f"cnc: {'line ' + str(number) + ' ' if number else ''}{line[:40]!r}… is "
                             f"{len(line) + 1} bytes, more than grbl's {self.capacity}-byte receive buffer")
        return line

    async def room(self, nbytes: int) -> None:
        """Wait until `nbytes` more fit grbl's RX buffer (or a refusal, an alarm or a stop ends the wait)."""
        while self.in_flight + nbytes > self.capacity:
            self.check_lost()
            if self.stream_error is not None or self.stream_alarm is not None or self.stopping:
                return
            await self.wait_changed()

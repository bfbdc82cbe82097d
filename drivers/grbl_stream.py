"""Character-counting streaming for the grbl driver (drivers/grbl.py: `CncLink.stream`).

The sum of `len(line) + 1` over unacknowledged lines stays at most the link's `capacity`
(grbl's RX ring less one byte); the next line goes as soon as an `ok` / `error:N` frees room.
The first `error:N` stops the sending and runs the link's safe stop (feed hold, reset, verified)
before GrblError is raised, so the lines already in grbl's buffer never run behind the refused
one and grbl is never left in Hold with lines queued. A safe stop called from elsewhere while
streaming breaks the stream off too (GrblStopped)."""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from drivers.grbl_errors import GrblAlarm, GrblError, GrblStopped
from drivers.grbl_status import Pending
from drivers.grbl_stop import SafeStopResult
from wire.grbl_protocol import Error, StreamResult, clean_line

if TYPE_CHECKING:
    from drivers.grbl import CncLink

__all__ = ["StreamRun"]

Progress = Callable[[int, int], None]


class StreamRun:
    """One `stream()` call: sends, drains, stops safely on an error, and raises what happened."""

    def __init__(self, link: CncLink, progress: Progress | None) -> None:
        self.link = link
        self.progress = progress
        self.res = StreamResult(capacity_bytes=link.capacity)
        self.ours: list[Pending] = []
        self.t0 = time.monotonic()
        self.gen = link._stop_gen
        self.acked_seen = 0
        self.stop: SafeStopResult | None = None

    def _halted(self) -> bool:
        """A safe stop began (ours or another caller's): send nothing more."""
        return self.link._stop_gen != self.gen

    async def run(self, lines: Iterable[str]) -> StreamResult:
        link = self.link
        async with link._send_lock:
            link._stream_error = None
            link._stream_alarm = None
            link._fill_area, link._fill_t, link._fill_max = 0.0, time.monotonic(), link._in_flight
            try:
                await self._send(lines)
                await self._drain()
                self._stats()
                self._raise_failure()
            finally:
                link._stream_error = None
        await link.command("G4 P0")  # sync point: ok only once all motion has finished
        self.res.elapsed_s = time.monotonic() - self.t0
        return self.res

    async def _send(self, lines: Iterable[str]) -> None:
        link = self.link
        for number, raw in enumerate(lines, 1):
            line = clean_line(raw)
            if not line:
                continue
            link._check_line(line, number)
            await link._room(len(line) + 1)
            if link._stream_error is not None or link._stream_alarm is not None or self._halted():
                return
            link._check_lost()
            self.ours.append(await link._send_line(line, number))
            self.res.lines += 1
            self.res.bytes_sent += len(line) + 1
            self._report_progress()

    def _report_progress(self) -> None:
        if self.progress is None:
            return
        acked = len(self.ours) - len(self.link._pending)
        if acked != self.acked_seen:
            self.acked_seen = acked
            self.progress(acked, len(self.ours))

    async def _stop_if_needed(self) -> None:
        """On our first error run the safe stop; on another caller's stop, wait for its result."""
        link = self.link
        if self.stop is not None:
            return
        err = link._stream_error
        if err is not None and not self._halted():
            r = err.future.result()
            code = r.code if isinstance(r, Error) else 0
            self.stop = await link.safe_stop(f"error:{code} at line {err.number} {err.line!r}")
        elif self._halted():
            self.stop = await link.safe_stop_result()

    async def _drain(self) -> None:
        """Every sent line answered, or failed by an alarm, a reset or the link's loss."""
        link = self.link
        for p in self.ours:
            while not p.future.done():
                if link._stream_error is not None or self._halted():
                    await self._stop_if_needed()
                    if p.future.done():
                        break
                await link._wait_changed()
            if p.future.exception() is not None:
                break
        if link._stream_error is not None or self._halted():
            await self._stop_if_needed()

    def _stats(self) -> None:
        link, res = self.link, self.res
        link._set_in_flight(link._in_flight)
        span = max(time.monotonic() - self.t0, 1e-9)
        res.mean_in_flight_bytes = link._fill_area / span
        res.max_in_flight_bytes = link._fill_max
        res.acked = sum(1 for p in self.ours if p.future.done() and not p.future.cancelled()
                        and p.future.exception() is None)
        if self.progress is not None:
            self.progress(res.acked, len(self.ours))

    def _raise_failure(self) -> None:
        link = self.link
        err = link._stream_error
        if err is not None:
            r = err.future.result()
            raise GrblError(r.code if isinstance(r, Error) else 0, err.line, err.number, link.url, safe_stop=self.stop)
        if self.stop is not None:
            raise GrblStopped(f"cnc at {link.url}: stream stopped after {self.res.acked} of {self.res.lines} line(s) "
                              f"sent: {self.stop.reason}; {self.stop.summary()}", self.stop)
        link._check_lost()
        for p in self.ours:
            exc = p.future.exception() if p.future.done() else None
            if exc is not None:
                raise exc
        for p in self.ours:
            if p.alarm is not None:
                raise GrblAlarm(p.alarm.code, p.line, link.url, f"; streamed up to line {p.number}")
        if link._stream_alarm is not None:
            raise GrblAlarm(link._stream_alarm.code, None, link.url)

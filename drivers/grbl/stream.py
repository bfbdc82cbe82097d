"""Character-counting streaming for the grbl driver (link.py: `CncLink.stream`).

The sum of `len(line) + 1` over unacknowledged lines stays at most the link's `capacity`
(grbl's RX ring less one byte); the next line goes as soon as an `ok` / `error:N` frees room.
The first `error:N` stops the sending and runs the link's safe stop (feed hold, reset, verified)
before GrblError is raised, so the lines already in grbl's buffer never run behind the refused
one and grbl is never left in Hold with lines queued. A safe stop called from elsewhere while
streaming breaks the stream off too (GrblStopped). The stream sends through the link's shared
`LinkState` (state.py) and asks the link, through `StreamOwner`, for the safe stop and the sync."""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import Protocol

from drivers.grbl.errors import GrblAlarm, GrblError, GrblStopped
from drivers.grbl.results import SafeStopResult
from drivers.grbl.state import LinkState
from drivers.grbl.status import Pending
from wire.grbl_protocol import Error, StreamResult, clean_line

__all__ = ["StreamRun", "StreamOwner"]

Progress = Callable[[int, int], None]


class StreamOwner(Protocol):
    """What a stream asks of its link (CncLink): a line awaited to its `ok`, and the safe stop."""

    async def command(self, line: str, timeout: float | None = None) -> list[str]: ...
    async def safe_stop(self, reason: str) -> SafeStopResult: ...
    async def safe_stop_result(self) -> SafeStopResult: ...


class StreamRun:
    """One `stream()` call: sends, drains, stops safely on an error, and raises what happened."""

    def __init__(self, shared: LinkState, link: StreamOwner, progress: Progress | None) -> None:
        self.sh = shared
        self.link = link
        self.progress = progress
        self.res = StreamResult(capacity_bytes=shared.capacity)
        self.ours: list[Pending] = []
        self.t0 = time.monotonic()
        self.gen = shared.stop_gen
        self.acked_seen = 0
        self.stop: SafeStopResult | None = None

    def _halted(self) -> bool:
        """A safe stop began (ours or another caller's): send nothing more."""
        return self.sh.stop_gen != self.gen

    async def run(self, lines: Iterable[str]) -> StreamResult:
        sh = self.sh
        async with sh.send_lock:
            sh.stream_error = None
            sh.stream_alarm = None
            sh.fill_area, sh.fill_t, sh.fill_max = 0.0, time.monotonic(), sh.in_flight
            try:
                await self._send(lines)
                await self._drain()
                self._stats()
                self._raise_failure()
            finally:
                sh.stream_error = None
        await self.link.command("G4 P0")  # sync point: ok only once all motion has finished
        self.res.elapsed_s = time.monotonic() - self.t0
        return self.res

    async def _send(self, lines: Iterable[str]) -> None:
        sh = self.sh
        for number, raw in enumerate(lines, 1):
            line = clean_line(raw)
            if not line:
                continue
            sh.check_line(line, number)
            await sh.room(len(line) + 1)
            if sh.stream_error is not None or sh.stream_alarm is not None or self._halted():
                return
            sh.check_lost()
            self.ours.append(await sh.send_line(line, number))
            self.res.lines += 1
            self.res.bytes_sent += len(line) + 1
            self._report_progress()

    def _report_progress(self) -> None:
        if self.progress is None:
            return
        acked = len(self.ours) - len(self.sh.pending)
        if acked != self.acked_seen:
            self.acked_seen = acked
            self.progress(acked, len(self.ours))

    async def _stop_if_needed(self) -> None:
        """On our first error run the safe stop; on another caller's stop, wait for its result."""
        if self.stop is not None:
            return
        err = self.sh.stream_error
        if err is not None and not self._halted():
            r = err.future.result()
            code = r.code if isinstance(r, Error) else 0
            self.stop = await self.link.safe_stop(f"error:{code} at line {err.number} {err.line!r}")
        elif self._halted():
            self.stop = await self.link.safe_stop_result()

    async def _drain(self) -> None:
        """Every sent line answered, or failed by an alarm, a reset or the link's loss."""
        sh = self.sh
        for p in self.ours:
            while not p.future.done():
                if sh.stream_error is not None or self._halted():
                    await self._stop_if_needed()
                    if p.future.done():
                        break
                await sh.wait_changed()
            if p.future.exception() is not None:
                break
        if sh.stream_error is not None or self._halted():
            await self._stop_if_needed()

    def _stats(self) -> None:
        sh, res = self.sh, self.res
        sh.set_in_flight(sh.in_flight)
        span = max(time.monotonic() - self.t0, 1e-9)
        res.mean_in_flight_bytes = sh.fill_area / span
        res.max_in_flight_bytes = sh.fill_max
        res.acked = sum(1 for p in self.ours if p.future.done() and not p.future.cancelled()
                        and p.future.exception() is None)
        if self.progress is not None:
            self.progress(res.acked, len(self.ours))

    def _raise_failure(self) -> None:
        sh = self.sh
        err = sh.stream_error
        if err is not None:
            r = err.future.result()
            raise GrblError(r.code if isinstance(r, Error) else 0, err.line, err.number, sh.url, safe_stop=self.stop)
        if self.stop is not None:
            raise GrblStopped(f"cnc at {sh.url}: stream stopped after {self.res.acked} of {self.res.lines} line(s) "
                              f"sent: {self.stop.reason}; {self.stop.summary()}", self.stop)
        sh.check_lost()
        for p in self.ours:
            exc = p.future.exception() if p.future.done() else None
            if exc is not None:
                raise exc
        for p in self.ours:
            if p.alarm is not None:
                raise GrblAlarm(p.alarm.code, p.line, sh.url, f"; streamed up to line {p.number}")
        if sh.stream_alarm is not None:
            raise GrblAlarm(sh.stream_alarm.code, None, sh.url)

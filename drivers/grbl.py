"""CncLink: the asyncio driver for a CNC speaking the grbl 1.1 serial interface (5 axes XYZAB).

Works unchanged against real grbl-interface firmware (plain grbl reports 3 axes: positions are
padded to 5 with 0.0) and against sims/cnc_sim.py. Talks bytes over any pyserial URL through
drivers/serial_async.py. Protocol details and choices: docs/protocols/grbl.md.

Flow control is grbl's character counting: the driver keeps the sum of the lengths of the
unacknowledged lines (each `len(line) + 1` for its `\\n`) at most `rx_buffer_bytes - 1`, the
usable size of grbl's RX ring, and sends the next line as soon as an `ok` / `error:N` frees
enough room, so the controller's buffer stays full. Real-time bytes (`?`, `!`, `~`, 0x18) are
not buffered by grbl and are sent at once. Status is polled in the background at
`status_hz` (at most 5 Hz, grbl's recommendation); no byte received for `link_timeout_s`
(grbl answers `?` even while moving, dwelling or homing) is a `LinkLost`.
"""
from __future__ import annotations

import asyncio
import re
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Iterable

from drivers.errors import DeviceError, DeviceTimeout, LinkLost
from wire.grbl_protocol import (
    AXES, POSITION_LOST_ALARMS, RT_CYCLE_START, RT_FEED_HOLD, RT_SOFT_RESET, RT_STATUS, Alarm, Banner,
    Error, GrblStatus, Ok, Pos5, Probe, StreamResult, alarm_meaning, clean_line, error_meaning, fmt,
    parse_line, parse_probe,
)
from drivers.serial_async import SerialPort
from core.errors import InputError

__all__ = ["CncLink", "GrblError", "GrblAlarm", "ProbeError", "GrblReset", "GrblAckLost", "GrblStatus", "ProbeResult",
           "StreamResult"]

# States in which a connect may soft-reset the controller to get its banner (nothing moves).
_RESETTABLE = ("Idle", "Alarm", "Check", "Sleep")


class GrblError(DeviceError):
    """grbl refused a line with `error:N`: `code`, `meaning`, the `line` text and, when
    streaming, its 1-based `line_number` in the streamed input."""

    def __init__(self, code: int, line: str, line_number: int | None = None, url: str = "") -> None:
        self.code = code
        self.meaning = error_meaning(code)
        self.line = line
        self.line_number = line_number
        where = f"line {line_number} " if line_number is not None else ""
        super().__init__(f"cnc{' at ' + url if url else ''}: {where}{line!r} refused with error:{code} "
                         f"({self.meaning})")


class GrblAlarm(DeviceError):
    """grbl raised `ALARM:N` (the machine is locked: `$X` unlock or `$H` home to go on)."""

    def __init__(self, code: int, line: str | None = None, url: str = "", detail: str = "") -> None:
        self.code = code
        self.meaning = alarm_meaning(code)
        self.line = line
        on = f" during {line!r}" if line else ""
        super().__init__(f"cnc{' at ' + url if url else ''}: ALARM:{code}{on} ({self.meaning}){detail}")


class ProbeError(GrblAlarm):
    """A probe cycle failed: ALARM:4 (probe already tripped) or ALARM:5 (no contact within travel)."""


class GrblAckLost(DeviceError):
    """grbl sits idle while lines are still unacknowledged: their `ok` was lost on the line."""


class _ReportSpan:
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


class GrblStuck(DeviceError):
    """grbl keeps reporting Idle but does not read the lines waiting in its RX buffer."""


class GrblReset(DeviceError):
    """The controller was reset (0x18 or power cycle) while lines were still unacknowledged."""


@dataclass(frozen=True)
class ProbeResult:
    """Where the probe tripped (machine coordinates x, y, z, a, b) and whether it touched."""

    position: Pos5
    contact: bool


@dataclass
class _Pending:
    line: str
    nbytes: int
    future: asyncio.Future
    number: int | None = None           # 1-based line number in a stream
    lines: list[str] = field(default_factory=list)
    alarm: Alarm | None = None
    sent_at: float = field(default_factory=time.monotonic)


def _dwell_s(line: str) -> float:
    """Seconds a `G4 P…` line may legitimately keep grbl busy while Idle (0 for other lines)."""
    u = line.upper().replace(" ", "")
    if "G4" not in u or "P" not in u:
        return 0.0
    try:
        return float(re.match(r"[-+]?[\d.]+", u.split("P", 1)[1]).group(0))  # type: ignore[union-attr]
    except (AttributeError, ValueError):
        return 0.0


class CncLink:
    """Driver for one grbl 1.1 controller.

    `CncLink(url, *, baud=115200, rx_buffer_bytes=128, status_hz=5.0)`; `await connect()`,
    `await close()`; `command(line)`, `stream(lines)`, `home()`, `unlock()`, `status()`,
    `feed_hold()`, `resume()`, `soft_reset()`, `wait_idle(timeout)`, `probe(target, feed)`.
    `latest_status` holds the newest background status report, `homed` whether `$H`
    succeeded since the position was last lost.
    """

    def __init__(self, url: str, *, baud: int = 115200, rx_buffer_bytes: int = 128, status_hz: float = 5.0,
                 link_timeout_s: float = 3.0, connect_timeout_s: float = 5.0, alarm_grace_s: float = 3.0,
                 ack_grace_s: float = 2.0, pace: bool = True, homing_timeout_s: float = 120.0,
                 stuck_after_s: float = 30.0, line_scale: float = 1.0) -> None:
        if not 0 < status_hz <= 5.0:
            raise ValueError("status_hz must be in (0, 5]: grbl recommends at most 5 status reports a second")
        if rx_buffer_bytes < 16:
            raise ValueError("rx_buffer_bytes must be at least 16")
        self.url = url
        self.baud = baud
        self.capacity = rx_buffer_bytes - 1   # a ring of N bytes holds N - 1
        self.status_period = 1.0 / status_hz
        self.link_timeout_s = link_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self.alarm_grace_s = alarm_grace_s
        self.ack_grace_s = ack_grace_s
        # grbl Idle with our bytes unread this long: stuck (grblHAL's spindle delays go up to 20 s)
        self.stuck_after_s = stuck_after_s
        self.homing_timeout_s = homing_timeout_s
        self._jogging = False     # a `$J=` was sent and may still be running
        self._quiet_until = 0.0   # grbl answers nothing during $H: no link/ack watchdog until then
        self._last_ack = time.monotonic()
        self._still = _ReportSpan()   # Idle / Alarm reports with grbl's RX buffer empty (or not reported)
        self._held = _ReportSpan()    # Idle / Alarm reports with bytes of ours still unread (Bf:)
        self._rx_free_max = 0         # the largest Bf: RX free seen: grbl's empty RX buffer
        self._last_sent = 0.0
        self._pace = pace
        # a simulated line at time scale k carries k times the bytes per wall second (DESIGN.md §6,
        # sims/transport.py): pace the writes to it as the robot link does (1 on hardware)
        self.line_scale = line_scale
        self._port = SerialPort(url, baud=baud, name="cnc", pace=pace, pace_factor=0.98 * line_scale)
        self.version: str | None = None
        self.firmware = "grbl"          # "Grbl 1.1h", "GrblHAL 1.1f" once the banner was seen
        self.rx_buffer_reported: int | None = None   # from `$I` [OPT:…,blocks,rx]
        self.latest_status: GrblStatus | None = None
        self.messages: deque[str] = deque(maxlen=200)   # unsolicited feedback lines
        self.alarms: list[int] = []
        self.last_probe: Probe | None = None
        self._homed = False
        self._pending: deque[_Pending] = deque()
        self._in_flight = 0
        self._buf = bytearray()
        self._wco: Pos5 | None = None
        self._lost: LinkLost | None = None
        self._last_rx = time.monotonic()
        self._last_q = 0.0
        self._status_waiters: list[asyncio.Future] = []
        self._banner_event = asyncio.Event()
        self.reset_at = 0.0  # wall time of the last banner (power-up/reset) or homing seen
        self._changed = asyncio.Event()
        self._send_lock = asyncio.Lock()
        self._tasks: list[asyncio.Task] = []
        self._closing = False
        # stream bookkeeping (time-weighted in-flight bytes)
        self._stream_error: _Pending | None = None
        self._stream_alarm: Alarm | None = None
        self._fill_area = 0.0
        self._fill_t = time.monotonic()
        self._fill_max = 0

    # -- properties ---------------------------------------------------------------------------
    @property
    def homed(self) -> bool:
        """True after a successful `$H` until an alarm or reset loses the machine position."""
        return self._homed

    @property
    def in_flight_bytes(self) -> int:
        """Bytes sent and not yet acknowledged (grbl's RX buffer as the driver counts it)."""
        return self._in_flight

    @property
    def connected(self) -> bool:
        return bool(self._tasks) and self._lost is None

    # -- lifecycle ----------------------------------------------------------------------------
    async def connect(self) -> GrblStatus:
        """Open the port, wait for (or provoke) the banner and read the state.

        A controller that prints its banner on open (USB boards reset when the port opens) is
        taken as is. Otherwise `?` is sent until a status report arrives; a controller that is
        not moving (Idle, Alarm) is then soft-reset to get its banner and a clean parser; one in
        motion (Run, Hold, Home, Jog) is attached to without a reset."""
        self._closing = False
        self._lost = None
        self.latest_status = None
        self._banner_event.clear()
        self._buf.clear()
        self._port = SerialPort(self.url, baud=self.baud, name="cnc", pace=self._pace,
                                pace_factor=0.98 * self.line_scale)
        await self._port.open()
        self._last_rx = time.monotonic()
        self._tasks = [asyncio.get_running_loop().create_task(self._read_loop())]
        deadline = time.monotonic() + self.connect_timeout_s
        try:
            while time.monotonic() < deadline and not self._banner_event.is_set() and self.latest_status is None:
                await self._write(RT_STATUS)
                self._last_q = time.monotonic()
                try:
                    await asyncio.wait_for(self._wait_changed(), 0.25)
                except asyncio.TimeoutError:
                    pass
                self._check_lost()
            if not self._banner_event.is_set():
                if self.latest_status is None:
                    raise DeviceTimeout(f"cnc at {self.url}: no answer to '?' within {self.connect_timeout_s:.1f} s; "
                                        "check the cable, the URL and that the controller is powered")
                if self.latest_status.state in _RESETTABLE:
                    for attempt in range(3):  # a banner garbled on the line: reset again
                        try:
                            await self.soft_reset(timeout=1.5)
                            break
                        except DeviceTimeout:
                            if attempt == 2:
                                raise
        except BaseException:
            await self.close()
            raise
        self._tasks.append(asyncio.get_running_loop().create_task(self._poll_loop()))
        st = await self.status()
        if st.state not in ("Run", "Hold", "Home", "Jog"):
            await self._read_build_info()
        return st

    async def _read_build_info(self) -> None:
        """`$I`: never fill grbl's RX ring beyond what the firmware says it has."""
        try:
            lines = await self.command("$I", timeout=5.0)
        except DeviceError:
            return
        for text in lines:
            m = re.match(r"\[OPT:[^,]*,(\d+),(\d+)", text)
            if m:
                self.rx_buffer_reported = int(m.group(2))
                self.capacity = min(self.capacity, self.rx_buffer_reported - 1)

    @property
    def axes(self) -> int:
        """Axes the controller has: the field count of its status report's position."""
        return self.latest_status.axes if self.latest_status is not None else 3

    def require_axes(self, letters: str, what: str) -> None:
        """Refuse (before any motion) `what` when it needs an axis this controller lacks."""
        have = "XYZAB"[:self.axes]
        lack = [c for c in letters.upper() if c not in have]
        if lack:
            raise DeviceError(f"cnc at {self.url}: {what} needs axis {', '.join(lack)} but {self.firmware} "
                              f"reports {self.axes} axes ({have}); use a controller with {'XYZAB'[:3 + len(lack)]} "
                              "or a 3-axis job")

    async def close(self) -> None:
        """Stop polling and close the port (the controller keeps running what it has)."""
        self._closing = True
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks = []
        self._port.close()
        self._fail_pending(LinkLost(f"cnc at {self.url}: link closed"))

    async def __aenter__(self) -> "CncLink":
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- receiving ----------------------------------------------------------------------------
    async def _read_loop(self) -> None:
        try:
            while True:
                data = await self._port.read()
                self._on_bytes(data)
        except LinkLost as exc:
            self._on_lost(exc)

    def _on_bytes(self, data: bytes) -> None:
        self._last_rx = time.monotonic()
        self._buf += data
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                break
            raw = bytes(self._buf[:i]).decode("ascii", "replace").strip()
            del self._buf[:i + 1]
            if raw:
                self._on_line(raw)
        if len(self._buf) > 4096:  # garbage without line ends: do not grow without bound
            del self._buf[:-256]
        self._pulse()

    def _on_line(self, text: str) -> None:
        r = parse_line(text, self._wco)
        if isinstance(r, GrblStatus):
            if r.wco is not None:
                self._wco = r.wco
            self.latest_status = r
            if r.rx_free is not None:   # Bf: (grblHAL by default): the most free is the empty buffer
                self._rx_free_max = max(self._rx_free_max, r.rx_free)
            # bytes still in grbl's RX buffer: it has not read all our lines yet (a spindle or
            # coolant change waits in a sync loop that keeps reporting Idle), so nothing is lost
            holding = r.rx_free is not None and r.rx_free < self._rx_free_max
            idle, now, activity = r.state in ("Idle", "Alarm"), time.monotonic(), self._last_activity()
            for span, on in ((self._held, idle and holding), (self._still, idle and not holding)):
                if on:
                    span.see(now, activity)
                else:
                    span.clear()
            waiters, self._status_waiters = self._status_waiters, []
            for f in waiters:
                if not f.done():
                    f.set_result(r)
        elif isinstance(r, (Ok, Error)):
            if not self._pending:
                return  # a stray acknowledgement (e.g. after a reset): nothing waits for it
            p = self._pending.popleft()
            self._last_ack = time.monotonic()
            self._set_in_flight(self._in_flight - p.nbytes)
            if isinstance(r, Error) and p.number is not None and self._stream_error is None:
                self._stream_error = p
            if not p.future.done():
                p.future.set_result(r)
        elif isinstance(r, Alarm):
            self.alarms.append(r.code)
            if r.code in POSITION_LOST_ALARMS:
                self._homed = False
            if self._pending:
                self._pending[0].alarm = r
                self._stream_alarm = self._stream_alarm or r
                # grbl still answers the lines it holds (a probe alarm: [PRB:…:0] then `ok` for
                # the G38 line after ~500 ms of silence; later lines `error:9`), or resets and
                # prints its banner. Replies stay matched to the lines sent; lines never
                # answered fail in _check_acks (Alarm state and quiet for ack_grace_s).
                self._last_ack = time.monotonic() + self.alarm_grace_s
            else:
                self.messages.append(text)
            # grbl sleeps after printing an alarm (delay_ms(500) in report_alarm_message) and
            # answers nothing, not even `?`: the watchdog allows that on top of link_timeout_s.
            self._last_rx = time.monotonic() + self.alarm_grace_s
        elif isinstance(r, Banner):
            self.version = r.version
            self.reset_at = time.time()  # power-up or reset: the table may not be where it was
            self.firmware = f"{r.name} {r.version}"
            self._banner_event.set()
            if self._pending and self._pending[0].alarm is not None:
                a = self._pending[0].alarm
                self._fail_pending(GrblAlarm(a.code, self._pending[0].line, self.url,
                                             " (grbl reset itself; the lines after it were flushed)"))
            self._fail_pending(GrblReset(f"cnc at {self.url}: controller reset (banner 'Grbl {r.version}') "
                                         "while lines were unacknowledged; they were flushed"))
        else:
            if isinstance(r, Probe):
                self.last_probe = r
            if self._pending:
                self._pending[0].lines.append(text)
            else:
                self.messages.append(text)

    def _fail_pending(self, exc: Exception) -> None:
        pend, self._pending = self._pending, deque()
        self._set_in_flight(0)
        for p in pend:
            if not p.future.done():
                p.future.set_exception(exc)
                p.future.exception()  # mark retrieved: nobody may be awaiting a stream's lines
        self._pulse()

    def _on_lost(self, exc: LinkLost) -> None:
        if self._closing:
            return
        self._lost = exc
        self._fail_pending(exc)
        for f in self._status_waiters:
            if not f.done():
                f.set_exception(exc)
                f.exception()
        self._status_waiters = []
        self._pulse()

    def _check_lost(self) -> None:
        if self._lost is not None:
            raise LinkLost(str(self._lost))
        if not self._tasks:
            raise LinkLost(f"cnc at {self.url}: not connected (call connect() first)")

    def _pulse(self) -> None:
        ev, self._changed = self._changed, asyncio.Event()
        ev.set()

    async def _wait_changed(self) -> None:
        await self._changed.wait()

    def _set_in_flight(self, n: int) -> None:
        now = time.monotonic()
        self._fill_area += self._in_flight * (now - self._fill_t)
        self._fill_t = now
        self._in_flight = max(n, 0)
        self._fill_max = max(self._fill_max, self._in_flight)

    # -- sending ------------------------------------------------------------------------------
    async def _write(self, data: bytes) -> None:
        if self._lost is not None:
            raise LinkLost(str(self._lost))
        await self._port.write(data)

    async def _send_line(self, line: str, number: int | None = None) -> _Pending:
        data = line.encode("ascii") + b"\n"
        p = _Pending(line, len(data), asyncio.get_running_loop().create_future(), number)
        self._pending.append(p)
        self._last_sent = p.sent_at
        self._set_in_flight(self._in_flight + p.nbytes)
        await self._write(data)
        return p

    def _check_line(self, line: str, number: int | None = None) -> str:
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

    async def _room(self, nbytes: int) -> None:
        while self._in_flight + nbytes > self.capacity:
            self._check_lost()
            if self._stream_error is not None or self._stream_alarm is not None:
                return
            await self._wait_changed()

    async def command(self, line: str, timeout: float | None = None) -> list[str]:
        """Send one line and await its `ok`; returns the lines grbl printed before it
        (`[GC:…]`, `$N=V`, `[PRB:…]`, `[MSG:…]`). `error:N` → GrblError; an ALARM raised
        while the line was pending → GrblAlarm (ProbeError for ALARM:4/5); no answer within
        `timeout` seconds (None: wait, the link watchdog still applies) → DeviceTimeout."""
        line = self._check_line(line.strip())
        self._check_lost()
        self._jogging = self._jogging or line.startswith("$J=")
        async with self._send_lock:
            self._stream_alarm = None
            await self._room(len(line) + 1)
            p = await self._send_line(line)
        try:
            r = await asyncio.wait_for(asyncio.shield(p.future), timeout)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"cnc at {self.url}: no answer to {line!r} within {timeout} s") from None
        if isinstance(r, Error):
            raise GrblError(r.code, line, url=self.url)
        if p.alarm is not None:
            cls = ProbeError if p.alarm.code in (4, 5) else GrblAlarm
            raise cls(p.alarm.code, line, self.url)
        return p.lines

    async def stream(self, lines: Iterable[str], progress: Callable[[int, int], None] | None = None) -> StreamResult:
        """Stream G-code with character counting, keeping grbl's RX buffer full.

        Comments and blank lines are stripped before sending (line numbers still count every
        input line). Stops sending at the first `error:N` and raises GrblError naming that
        line's number and text (the lines already in grbl's buffer still run, as they do on the
        real controller; their answers are collected first). An ALARM stops the stream with
        GrblAlarm. On success it sends `G4 P0` and returns once everything sent has executed.
        `progress(acked, sent)` is called as acknowledgements arrive."""
        self._check_lost()
        res = StreamResult(capacity_bytes=self.capacity)
        ours: list[_Pending] = []
        t0 = time.monotonic()
        async with self._send_lock:
            self._stream_error = None
            self._stream_alarm = None
            self._fill_area, self._fill_t, self._fill_max = 0.0, time.monotonic(), self._in_flight
            acked_seen = 0
            try:
                for number, raw in enumerate(lines, 1):
                    line = clean_line(raw)
                    if not line:
                        continue
                    self._check_line(line, number)
                    await self._room(len(line) + 1)
                    if self._stream_error is not None or self._stream_alarm is not None:
                        break
                    self._check_lost()
                    ours.append(await self._send_line(line, number))
                    res.lines += 1
                    res.bytes_sent += len(line) + 1
                    if progress is not None:
                        acked = len(ours) - len(self._pending)
                        if acked != acked_seen:
                            acked_seen = acked
                            progress(acked, len(ours))
                # drain: every sent line answered (or failed by an alarm, reset or link loss)
                for p in ours:
                    try:
                        await p.future
                    except DeviceError:
                        break
                self._set_in_flight(self._in_flight)
                span = max(time.monotonic() - t0, 1e-9)
                res.mean_in_flight_bytes = self._fill_area / span
                res.max_in_flight_bytes = self._fill_max
                res.acked = sum(1 for p in ours if p.future.done() and not p.future.cancelled()
                                and p.future.exception() is None)
                if progress is not None:
                    progress(res.acked, len(ours))
                self._check_lost()
                for p in ours:
                    if p.future.done() and p.future.exception() is not None:
                        raise p.future.exception()  # type: ignore[misc]
                err = self._stream_error
                if err is not None:
                    r = err.future.result()
                    raise GrblError(r.code, err.line, err.number, self.url)
                for p in ours:
                    if p.alarm is not None:
                        raise GrblAlarm(p.alarm.code, p.line, self.url, f"; streamed up to line {p.number}")
                if self._stream_alarm is not None:
                    raise GrblAlarm(self._stream_alarm.code, None, self.url)
            finally:
                self._stream_error = None
        await self.command("G4 P0")  # sync point: ok only once all motion has finished
        res.elapsed_s = time.monotonic() - t0
        return res

    # -- real-time commands -------------------------------------------------------------------
    async def feed_hold(self) -> None:
        """`!`: decelerate to a stop (Hold:1, then Hold:0); queued lines are kept."""
        self._check_lost()
        await self._write(RT_FEED_HOLD)

    async def resume(self) -> None:
        """`~`: cycle start / resume after a feed hold."""
        self._check_lost()
        await self._write(RT_CYCLE_START)

    async def soft_reset(self, timeout: float = 5.0) -> None:
        """0x18: grbl stops at once, flushes its buffers and prints its banner again.

        Unacknowledged lines fail with GrblReset. Resetting while moving loses the position
        (grbl answers ALARM:3 and stays in Alarm)."""
        self._check_lost()
        self._banner_event.clear()
        await self._write(RT_SOFT_RESET)
        try:
            await asyncio.wait_for(self._banner_event.wait(), timeout)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"cnc at {self.url}: no banner within {timeout} s after a soft reset") from None
        self._fail_pending(GrblReset(f"cnc at {self.url}: soft reset flushed the unacknowledged lines"))

    # -- status -------------------------------------------------------------------------------
    def _check_acks(self, now: float) -> None:
        """Fail the pending lines when grbl has kept reporting Idle (or Alarm) without answering
        them for longer than `ack_grace_s` plus any dwell they ask for: a standing grbl answers
        every line in its buffer within milliseconds, so their `ok` was lost (grbl has no
        checksums). The span is between the receipt of the first Idle report after our last line
        or 'ok' and the newest one: a firmware starved of CPU (silent, or its held reports
        arriving in one burst) is left to the link timeout, not called a lost 'ok'. Where grbl
        reports its buffers (Bf:, grblHAL's default) a report with bytes still in its RX buffer is
        not a standing grbl: it has lines of ours to read, and the span starts again."""
        if not self._pending or now < self._quiet_until:
            return
        activity = self._last_activity()
        dwell = sum(_dwell_s(p.line) for p in self._pending)
        held = self._held.length(activity)
        if held is not None and held > self.stuck_after_s + dwell:
            st = self.latest_status
            self._fail_pending(GrblStuck(
                f"cnc at {self.url}: grbl has reported Idle for {held:.0f} s with "
                f"{self._rx_free_max - (st.rx_free or 0) if st else '?'} byte(s) of ours unread in its RX buffer "
                f"and {len(self._pending)} line(s) from {self._pending[0].line!r} on unanswered: the firmware "
                "stopped reading its input; soft reset it (or power-cycle the controller)"))
            return
        still = self._still.length(activity)
        if still is not None and still > self.ack_grace_s + dwell:
            n = len(self._pending)
            a = self._pending[0].alarm
            if a is not None:   # the alarm's own line was never answered (hard limit, abort)
                self._fail_pending((ProbeError if a.code in (4, 5) else GrblAlarm)(a.code, self._pending[0].line, self.url))
                return
            self._fail_pending(GrblAckLost(
                f"cnc at {self.url}: grbl is {self.latest_status.state if self.latest_status else '?'}{self._rx_note()} but "
                f"{n} line(s) from {self._pending[0].line!r} on were never acknowledged (an 'ok' was lost "
                "on the line); check the cable, then re-sync with a soft reset"))

    def _last_activity(self) -> float:
        """When we last sent a line or grbl last answered one."""
        return max(self._last_sent, self._last_ack)

    def _rx_note(self) -> str:
        st = self.latest_status
        if st is None or st.rx_free is None:
            return ""
        return f" with its RX buffer empty (Bf: {st.rx_free} bytes free)"

    async def _poll_loop(self) -> None:
        while True:
            await asyncio.sleep(self.status_period / 2)
            now = time.monotonic()
            self._check_acks(now)
            if now - self._last_rx > self.link_timeout_s and now >= self._quiet_until:
                self._port.close()
                self._on_lost(LinkLost(f"cnc at {self.url}: silent for {self.link_timeout_s:.1f} s "
                                       "(no answer to status requests); check the cable and the controller"))
                return
            if now - self._last_q >= self.status_period * 0.999:
                self._last_q = now
                try:
                    await self._write(RT_STATUS)
                except LinkLost as exc:
                    self._on_lost(exc)
                    return

    async def status(self, timeout: float | None = None) -> GrblStatus:
        """A fresh status report (the next one the ≤ 5 Hz poll brings in)."""
        self._check_lost()
        fut = asyncio.get_running_loop().create_future()
        self._status_waiters.append(fut)
        now = time.monotonic()
        if now - self._last_q >= self.status_period:
            self._last_q = now
            await self._write(RT_STATUS)
        try:
            return await asyncio.wait_for(fut, timeout or self.link_timeout_s + self.status_period)
        except asyncio.TimeoutError:
            raise DeviceTimeout(f"cnc at {self.url}: no status report; check the link") from None

    async def wait_idle(self, timeout: float = 60.0) -> GrblStatus:
        """Wait until all motion has finished and the controller is Idle (G4 P0, then status)."""
        deadline = time.monotonic() + timeout
        st = self.latest_status
        if st is not None and st.state == "Jog" or self._jogging:
            st = await self.status()   # grbl refuses G-code (error:9) while jogging: poll instead
        self._jogging = False
        if st is None or st.state not in ("Alarm", "Jog"):
            try:
                await self.command("G4 P0", timeout=max(deadline - time.monotonic(), 0.01))
            except DeviceTimeout:
                raise DeviceTimeout(f"cnc at {self.url}: not idle within {timeout} s "
                                    f"(state {self.latest_status.state if self.latest_status else '?'})") from None
        while True:
            st = await self.status()
            if st.state == "Idle":
                return st
            if st.state == "Jog":
                continue
            if st.state == "Alarm":
                raise GrblAlarm(self.alarms[-1] if self.alarms else 0, None, self.url, "; unlock ($X) or home ($H)")
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"cnc at {self.url}: not idle within {timeout} s (state {st.state})")

    # -- machine commands ---------------------------------------------------------------------
    async def home(self, timeout: float | None = None) -> GrblStatus:
        """`$H`: run the homing cycle, answered once homing has finished. grbl answers nothing
        (not even `?`) meanwhile, so the link watchdog waits `timeout` (default
        `homing_timeout_s`, cell.yaml) instead of `link_timeout_s`."""
        limit = self.homing_timeout_s if timeout is None else timeout
        self._quiet_until = time.monotonic() + limit
        try:
            await self.command("$H", timeout=limit)
        except DeviceTimeout:
            raise DeviceTimeout(f"cnc at {self.url}: homing ($H) not finished within {limit:.0f} s "
                                "(cnc.homing_timeout_s in cell.yaml); check the limit switches") from None
        finally:
            self._quiet_until = 0.0
            self._last_rx = time.monotonic()
        self._homed = True
        self.reset_at = time.time()  # homing: an alignment probed before it no longer holds
        return await self.status()

    async def unlock(self) -> list[str]:
        """`$X`: clear the alarm lock ("[MSG:Caution: Unlocked]"); the position is not re-homed."""
        return await self.command("$X")

    async def _recover_probe(self, start: GrblStatus) -> str:
        """After a failed probe: `$X`, retract Z to where the probe started (machine
        coordinates), and confirm Idle from a status report. Returns a note for the error."""
        try:
            await self.command("$X")
            await self.command(f"G53 G0 Z{fmt(start.mpos[2])}")
            st = await self.wait_idle(30.0)
        except DeviceError as e:
            return f"; recovery failed ({e}): unlock ($X) and retract by hand"
        return f"; recovered: unlocked, Z retracted to {start.mpos[2]:.3f} (machine), state {st.state}"

    async def probe(self, target: dict[str, float] | tuple[float, float, float], feed_mm_min: float, *,
                    mode: str = "G38.2", unlock_on_fail: bool = True) -> ProbeResult:
        """Probe toward `target` (absolute, G90, in the active work coordinates; with grbl's
        default G54 offsets of zero these are machine coordinates) at `feed_mm_min`.

        Returns the trip position in machine coordinates ([PRB:…]) and `contact`. G38.2 without
        contact (ALARM:5) or with the probe already tripped (ALARM:4) raises ProbeError; by
        default the alarm lock is then cleared with `$X` (probe alarms do not lose position).
        G38.3 returns `contact=False` on a miss."""
        if mode not in ("G38.2", "G38.3", "G38.4", "G38.5"):
            raise InputError(f"cnc probe: mode {mode!r}; use G38.2 or G38.3")
        if not feed_mm_min > 0:
            raise InputError(f"cnc probe: feed {feed_mm_min} mm/min must be positive")
        if isinstance(target, dict):
            items = []
            for k, v in target.items():
                if k.lower() not in AXES:
                    raise InputError(f"cnc probe: unknown axis {k!r}; use x, y, z, a, b")
                items.append((k.upper(), float(v)))
        else:
            items = list(zip("XYZ", (float(v) for v in target)))
        words = " ".join(f"{k}{fmt(v)}" for k, v in items)
        line = f"{mode} G90 {words} F{feed_mm_min:g}"
        where = f" toward {words}"
        start = await self.status()
        try:
            lines = await self.command(line)
        except ProbeError as exc:
            hint = ("; back off before probing again" if exc.code == 4
                    else "; check the travel, the part's position and the probe")
            if unlock_on_fail:
                hint += await self._recover_probe(start)
            raise ProbeError(exc.code, line, self.url, where + hint) from None
        for text in reversed(lines):
            if text.startswith("[PRB:"):
                prb = parse_probe(text)
                return ProbeResult(prb.position, prb.success)
        raise DeviceError(f"cnc at {self.url}: {line!r} answered without a [PRB:…] report")

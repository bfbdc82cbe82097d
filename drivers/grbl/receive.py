"""The receiving half of the grbl driver (`link.py`: CncLink builds on it): every line
grbl prints is parsed (wire/grbl_protocol.py) and dispatched by its kind to one handler: status
reports (position, state, `Bf:` buffers, the spans the acknowledgement watchdog judges),
`ok` / `error:N` (matched in order to the lines sent), `ALARM:N`, the banner (a reset) and
bracketed feedback. Also what the reports tell about the machine: its axes and buffer sizes."""
from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from typing import Any

from drivers.errors import LinkLost
from drivers.grbl.errors import GrblAckLost, GrblAlarm, GrblAxesMissing, GrblReset, GrblStuck, ProbeError
from drivers.grbl.state import LinkState
from drivers.grbl.status import ReportSpan, dwell_s
from wire.grbl_protocol import POSITION_LOST_ALARMS, Alarm, Banner, Error, GrblStatus, Ok, Pos5, Probe, Reply, parse_line

__all__ = ["GrblReceiver"]


class GrblReceiver:
    """State heard from one grbl controller and the handlers that keep it; CncLink sends.
    `shared` is what the driver's parts share (state.py)."""

    def __init__(self, shared: LinkState, *, alarm_grace_s: float, ack_grace_s: float, stuck_after_s: float) -> None:
        self.shared = shared
        self.url = shared.url
        self.alarm_grace_s = alarm_grace_s
        self.ack_grace_s = ack_grace_s
        # grbl Idle with our bytes unread this long: stuck (grblHAL's spindle delays go up to 20 s)
        self.stuck_after_s = stuck_after_s
        self._last_ack = time.monotonic()
        self._still = ReportSpan()   # Idle / Alarm reports with grbl's RX buffer empty (or not reported)
        self._held = ReportSpan()    # Idle / Alarm reports with bytes of ours still unread (Bf:)
        self._rx_free_max = 0         # the largest Bf: RX free seen: grbl's empty RX buffer
        self._planner_free_max = 0    # the largest Bf: planner free seen: grbl's empty planner
        self.version: str | None = None
        self.firmware = "grbl"          # "Grbl 1.1h", "GrblHAL 1.1f" once the banner was seen
        self.rx_buffer_reported: int | None = None   # from `$I` [OPT:…,blocks,rx]
        self.planner_blocks_reported: int | None = None   # idem
        self.axis_letters: str | None = None         # from `$I` [AXS:n:XYZAB] (grblHAL)
        self.latest_status: GrblStatus | None = None
        self.status_t = 0.0   # when latest_status came off the wire (the port's reader thread), monotonic
        self.answer_t = 0.0   # when the latest `ok` / `error:N` came off the wire, monotonic
        self.messages: deque[str] = deque(maxlen=200)   # unsolicited feedback lines
        self.alarms: list[int] = []
        self.last_probe: Probe | None = None
        self._wco: Pos5 | None = None
        self.reset_at = 0.0  # wall time of the last banner (power-up/reset) or homing seen
        self._handlers: dict[type, Callable[[Any, str], None]] = {
            GrblStatus: self._on_status, Ok: self._on_answer, Error: self._on_answer, Alarm: self._on_alarm,
            Banner: self._on_banner}

    @property
    def homed(self) -> bool:
        """True after a successful `$H` until an alarm or reset loses the machine position."""
        return self.shared.homed

    @property
    def in_flight_bytes(self) -> int:
        """Bytes sent and not yet acknowledged (grbl's RX buffer as the driver counts it)."""
        return self.shared.in_flight

    @property
    def planner_blocks_empty(self) -> int:
        """Planner blocks free in a `Bf:` report when nothing is queued."""
        return max(self.planner_blocks_reported or 0, self._planner_free_max)

    @property
    def rx_free_empty(self) -> int:
        """RX bytes free in a `Bf:` report when nothing is queued (grbl 128, grblHAL 1023)."""
        return self._rx_free_max

    @property
    def axes(self) -> int:
        """Axes the controller has: the field count of its status report's position."""
        return self.latest_status.axes if self.latest_status is not None else 3

    @property
    def axis_count(self) -> int:
        """The same as `axes` (read from the status report at connect)."""
        return self.axes

    @property
    def axis_names(self) -> str:
        """The controller's axis letters: `$I`'s [AXS:…] when reported, else XYZAB cut to `axes`."""
        if self.axis_letters and len(self.axis_letters) == self.axes:
            return self.axis_letters
        return "XYZABC"[:self.axes]

    def require_axes(self, names: str, why: str) -> None:
        """Refuse, before any motion, `why` (e.g. "job part.yaml") when it needs an axis of
        `names` (e.g. "XYZAB") that this controller lacks: GrblAxesMissing names the firmware,
        the axes it has and those it lacks."""
        have = self.axis_names
        need = "".join(dict.fromkeys(c for c in names.upper() if c.isalpha()))
        if self.axis_letters is None or len(self.axis_letters) != self.axes:
            # the firmware does not name its axes (grbl 1.1h, a grblHAL without [AXS]): its status
            # report's position count is all that is known, so the 4th/5th rotary axes are judged
            # by count (an A/C table's C is its 5th axis)
            lack = need[self.axes:] if len(need) > self.axes else ""
        else:
            lack = "".join(c for c in need if c not in have)
        if not lack:
            return
        n = len(set(have) | set(need))
        raise GrblAxesMissing(
            f"{self.firmware} on {self.url}: {len(have)} axes ({' '.join(have)}); {why} needs {' '.join(lack)} "
            f"({n}-axis); use a {n}-axis firmware such as grblHAL", self.firmware, have, lack)

    def _on_bytes(self, data: bytes) -> None:
        sh = self.shared
        sh.last_rx = time.monotonic()
        sh.buf += data
        while True:
            i = sh.buf.find(b"\n")
            if i < 0:
                break
            raw = bytes(sh.buf[:i]).decode("ascii", "replace").strip()
            del sh.buf[:i + 1]
            if raw:
                self._on_line(raw)
        if len(sh.buf) > 4096:  # garbage without line ends: do not grow without bound
            del sh.buf[:-256]
        sh.pulse()

    def _on_line(self, text: str) -> None:
        r: Reply = parse_line(text, self._wco)
        self._handlers.get(type(r), self._on_feedback)(r, text)

    def _on_status(self, r: GrblStatus, text: str) -> None:
        if r.wco is not None:
            self._wco = r.wco
        self.latest_status = r
        self.status_t = self.shared.port.rx_t or time.monotonic()
        if r.rx_free is not None and r.planner_free is not None:
            # Bf: the most free ever seen is the empty buffer / planner
            self._rx_free_max = max(self._rx_free_max, r.rx_free)
            self._planner_free_max = max(self._planner_free_max, r.planner_free)
        # bytes still in grbl's RX buffer: it has not read all our lines yet (a spindle or
        # coolant change waits in a sync loop that keeps reporting Idle), so nothing is lost
        holding = r.rx_free is not None and r.rx_free < self._rx_free_max
        idle, now, activity = r.state in ("Idle", "Alarm"), time.monotonic(), self._last_activity()
        for span, on in ((self._held, idle and holding), (self._still, idle and not holding)):
            if on:
                span.see(now, activity)
            else:
                span.clear()
        waiters, self.shared.status_waiters = self.shared.status_waiters, []
        for f in waiters:
            if not f.done():
                f.set_result(r)

    def _on_answer(self, r: Ok | Error, text: str) -> None:
        sh = self.shared
        if not sh.pending:
            return  # a stray acknowledgement (e.g. after a reset): nothing waits for it
        p = sh.pending.popleft()
        self._last_ack = time.monotonic()
        self.answer_t = sh.port.rx_t or self._last_ack
        sh.set_in_flight(sh.in_flight - p.nbytes)
        if isinstance(r, Error) and p.number is not None and sh.stream_error is None:
            sh.stream_error = p
        if not p.future.done():
            p.future.set_result(r)

    def _on_alarm(self, r: Alarm, text: str) -> None:
        sh = self.shared
        self.alarms.append(r.code)
        if r.code in POSITION_LOST_ALARMS:
            sh.homed = False
        if sh.pending:
            sh.pending[0].alarm = r
            sh.stream_alarm = sh.stream_alarm or r
            # grbl still answers the lines it holds (a probe alarm: [PRB:…:0] then `ok` for
            # the G38 line after ~500 ms of silence; later lines `error:9`), or resets and
            # prints its banner. Replies stay matched to the lines sent; lines never
            # answered fail in _check_acks (Alarm state and quiet for ack_grace_s).
            self._last_ack = time.monotonic() + self.alarm_grace_s
        else:
            self.messages.append(text)
        # grbl sleeps after printing an alarm (delay_ms(500) in report_alarm_message) and
        # answers nothing, not even `?`: the watchdog allows that on top of link_timeout_s.
        sh.last_rx = time.monotonic() + self.alarm_grace_s

    def _on_banner(self, r: Banner, text: str) -> None:
        self.version = r.version
        self.reset_at = time.time()  # power-up or reset: the table may not be where it was
        self.firmware = f"{r.name} {r.version}"
        sh = self.shared
        sh.banner.set()
        if sh.pending and sh.pending[0].alarm is not None:
            a = sh.pending[0].alarm
            sh.fail_pending(GrblAlarm(a.code, sh.pending[0].line, self.url,
                                      " (grbl reset itself; the lines after it were flushed)"))
        sh.fail_pending(GrblReset(f"cnc at {self.url}: controller reset (banner '{r.name} {r.version}') "
                                     "while lines were unacknowledged; they were flushed"))

    def _on_feedback(self, r: Reply, text: str) -> None:
        if isinstance(r, Probe):
            self.last_probe = r
        if self.shared.pending:
            self.shared.pending[0].lines.append(text)
        else:
            self.messages.append(text)

    def _on_lost(self, exc: LinkLost) -> None:
        sh = self.shared
        if sh.closing:
            return
        sh.lost = exc
        sh.fail_pending(exc)
        for f in sh.status_waiters:
            if not f.done():
                f.set_exception(exc)
                f.exception()
        sh.status_waiters = []
        sh.pulse()

    def _check_acks(self, now: float) -> None:
        """Fail the pending lines when grbl has kept reporting Idle (or Alarm) without answering
        them for longer than `ack_grace_s` plus any dwell they ask for: a standing grbl answers
        every line in its buffer within milliseconds, so their `ok` was lost (grbl has no
        checksums). The span is between the receipt of the first Idle report after our last line
        or 'ok' and the newest one: a firmware starved of CPU (silent, or its held reports
        arriving in one burst) is left to the link timeout, not called a lost 'ok'. Where grbl
        reports its buffers (Bf:, grblHAL's default) a report with bytes still in its RX buffer is
        not a standing grbl: it has lines of ours to read, and the span starts again."""
        sh = self.shared
        if not sh.pending or now < sh.quiet_until:
            return
        activity = self._last_activity()
        dwell = sum(dwell_s(p.line) for p in sh.pending)
        held = self._held.length(activity)
        if held is not None and held > self.stuck_after_s + dwell:
            st = self.latest_status
            sh.fail_pending(GrblStuck(
                f"cnc at {self.url}: grbl has reported Idle for {held:.0f} s with "
                f"{self._rx_free_max - (st.rx_free or 0) if st else '?'} byte(s) of ours unread in its RX buffer "
                f"and {len(sh.pending)} line(s) from {sh.pending[0].line!r} on unanswered: the firmware "
                "stopped reading its input; soft reset it (or power-cycle the controller)"))
            return
        still = self._still.length(activity)
        if still is not None and still > self.ack_grace_s + dwell:
            n = len(sh.pending)
            a = sh.pending[0].alarm
            if a is not None:   # the alarm's own line was never answered (hard limit, abort)
                sh.fail_pending((ProbeError if a.code in (4, 5) else GrblAlarm)(a.code, sh.pending[0].line, self.url))
                return
            sh.fail_pending(GrblAckLost(
                f"cnc at {self.url}: grbl is {self.latest_status.state if self.latest_status else '?'}{self._rx_note()} but "
                f"{n} line(s) from {sh.pending[0].line!r} on were never acknowledged (an 'ok' was lost "
                "on the line); check the cable, then re-sync with a soft reset"))

    def _last_activity(self) -> float:
        """When we last sent a line or grbl last answered one."""
        return max(self.shared.last_sent, self._last_ack)

    def _rx_note(self) -> str:
        st = self.latest_status
        if st is None or st.rx_free is None:
            return ""
        return f" with its RX buffer empty (Bf: {st.rx_free} bytes free)"

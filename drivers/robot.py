"""RobotLink: the asyncio host side of RLP/1 (DESIGN.md §5, docs/protocols/rlp.md).

Moves are numbered with *tickets*: unwrapped, monotonically increasing ints whose low 16 bits
are the wire sequence number, so a job of any length is journaled unambiguously. The link keeps
a sliding window bounded by the robot's queue (credits), takes cumulative ACKs, goes back to the
NAKed frame at once (go-back-N, as the robot discards what follows a bad frame), retransmits on
an adaptive timeout (Jacobson/Karn), sends control frames ahead of the queue, watches the
heartbeat (link lost after `link_timeout_s` of silence or when the port closes), and after a
reconnect resynchronises from the robot's last received / last executed sequence numbers.

Usage (the controller's build executor):
    link = RobotLink(url)
    st = await link.connect(resume_ticket=journaled_ticket_or_None)
    t = await link.send_move("MOVL", x, y, z, i, j, k, v)   # back-pressure: waits for window space
    await link.wait_executed(t)
Waiters get LinkLost (naming the device and URL) when the link drops; with auto_reconnect the
link reconnects in the background and emits `link_restored` (motion held by the robot's silence
rule stays held until `go()`).
"""
from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass, field
from typing import AsyncIterator, Callable

from wire import rlp
from drivers.robot_guard import GARBLED_RUN, MAX_HB_PER_READ, MAX_OWN_PER_READ, SUSPECT_S, FloodMeter, split_lines
from drivers.errors import DeviceError, DeviceTimeout, LinkLost
from drivers.serial_async import SerialPort

_HOLD_FRAME = rlp.encode("!HOLD")

@dataclass(frozen=True)
class RobotStatus:
    """The robot's answer to a control frame (STA), with the sequence numbers as tickets too."""

    state: str
    last_rx: int
    last_exec: int
    queue_free: int
    pos: tuple[float, float, float]
    last_rx_ticket: int = 0
    last_exec_ticket: int = 0


@dataclass(frozen=True)
class RobotEvent:
    """kind: EXE (ticket), MRK (value n), ERR (value code, text), HB (value n), STA (status),
    link_lost (text), link_restored (status)."""

    kind: str
    ticket: int | None = None
    value: object = None
    text: str = ""
    t: float = 0.0


@dataclass
class LinkStats:
    frames_sent: int = 0
    frames_received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    resends: int = 0
    timeouts: int = 0
    crc_errors: int = 0      # robot frames received with a bad CRC
    bad_frames: int = 0      # robot frames with a bad syntax
    naks: int = 0            # NAKs received from the robot
    naks_by_reason: dict = field(default_factory=dict)
    reconnects: int = 0
    heartbeats: int = 0      # HB-looking lines received (a flood counts every one)
    hb_skipped: int = 0      # of those, not decoded (over the per-read bound)
    protocol_faults: int = 0
    rtt_s: deque = field(default_factory=lambda: deque(maxlen=2000))

    @property
    def rtt_ms_mean(self) -> float:
        return 1000.0 * sum(self.rtt_s) / len(self.rtt_s) if self.rtt_s else float("nan")

    @property
    def rtt_ms_p99(self) -> float:
        if not self.rtt_s:
            return float("nan")
        s = sorted(self.rtt_s)
        return 1000.0 * s[min(len(s) - 1, int(0.99 * len(s)))]

    def as_dict(self) -> dict:
        return {"frames_sent": self.frames_sent, "frames_received": self.frames_received,
                "bytes_sent": self.bytes_sent, "bytes_received": self.bytes_received,
                "resends": self.resends, "timeouts": self.timeouts, "crc_errors": self.crc_errors,
                "bad_frames": self.bad_frames, "naks": self.naks, "naks_by_reason": dict(self.naks_by_reason),
                "reconnects": self.reconnects, "heartbeats": self.heartbeats, "hb_skipped": self.hb_skipped,
                "protocol_faults": self.protocol_faults,
                "rtt_ms_mean": round(self.rtt_ms_mean, 3), "rtt_ms_p99": round(self.rtt_ms_p99, 3)}


class RobotLink:
    """The robot link driver. All methods are coroutines on one event loop."""

    TICK_S = 0.02  # retransmit / link-loss / keepalive check period

    def __init__(self, url: str, *, baud: int = 115200, link_timeout_s: float = 3.0, name: str = "robot",
                 pace: bool = True, max_inflight: int | None = None, auto_reconnect: bool = True,
                 keepalive_s: float = 0.5, control_timeout_s: float = 0.25,
                 rto_min_s: float = 0.1, rto_max_s: float = 1.0, line_scale: float = 1.0) -> None:
        self.url = url
        self.baud = baud
        # a simulated line at time scale k carries k times the bytes per wall second (DESIGN.md §6):
        # pace the writes at that rate, or the host, not the line, starves the bead
        self.line_scale = line_scale
        self.name = name
        self.link_timeout_s = link_timeout_s
        self.pace = pace
        self.max_inflight = max_inflight   # 1: send-and-wait (the benchmark's baseline)
        self.auto_reconnect = auto_reconnect
        self.keepalive_s = keepalive_s
        self.control_timeout_s = control_timeout_s
        self.rto_min_s, self.rto_max_s = rto_min_s, rto_max_s
        self.stats = LinkStats()
        self.last_status: RobotStatus | None = None
        self.fault: str | None = None
        self._rx_t: float | None = None     # arrival time of the chunk being parsed
        self._port: SerialPort | None = None
        self._connected = False
        self._ready = False                # connected and resynchronised
        self._closing = False
        self._history = False              # tickets already assigned in this session
        self._next_ticket = 1              # the ticket send_move assigns next
        self._send_next = 1                # the ticket the sender transmits next
        self._last_ack = 0
        self._last_exec = 0
        self._window_end = 0               # highest ticket the robot's queue can take now
        self._capacity = 0
        self._frames: dict[int, bytes] = {}
        self._sent_at: dict[int, float] = {}
        self._retx: set[int] = set()
        self._ctrl: deque[bytes] = deque()
        self._tx_paused = False
        self._srtt: float | None = None
        self._rttvar = 0.0
        self._rto = 0.25
        self._min_rtt: float | None = None
        self._last_heard = 0.0
        self._last_tx = 0.0
        self._kick = asyncio.Event()
        self._change = asyncio.Event()
        self._tasks: list[asyncio.Task] = []
        self._reconnect_task: asyncio.Task | None = None
        self._ctrl_lock = asyncio.Lock()
        self._callbacks: list[Callable[[RobotEvent], None]] = []
        self._queues: list[asyncio.Queue] = []
        self._lost: LinkLost | None = None
        self._sta_seen: rlp.Reply | None = None
        self._aborted_below = 0            # tickets below this and not executed were flushed
        self._max_sent = 0                 # highest ticket ever transmitted (an ACK/EXE above: a lie)
        self._bad_at_ack = 0               # bad frames received up to the last ACK
        self._flood = FloodMeter()
        self.protocol_fault: str | None = None  # latched: holds motion until reset()
        self._bad_run = 0                  # consecutive bad frames (no valid one between)
        self._suspect_held = False         # we wrote !HOLD because the robot went quiet
        self.held_at: float | None = None  # monotonic time the link itself last wrote !HOLD
        # when !HOLD frames actually went out on the line (a bead cut blind is timed to the first)
        self.hold_tx: deque[float] = deque(maxlen=16)

    # -- public properties ---------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True once connect() has resynchronised, until the link is lost."""
        return self._connected and self._ready

    @property
    def last_exec_ticket(self) -> int:
        return self._last_exec

    @property
    def last_ack_ticket(self) -> int:
        return self._last_ack

    @property
    def next_ticket(self) -> int:
        return self._next_ticket

    @property
    def rto_s(self) -> float:
        return self._rto

    # -- events ---------------------------------------------------------------------------------
    def on_event(self, fn: Callable[[RobotEvent], None]) -> None:
        """Call `fn(event)` for every event (EXE, MRK, ERR, HB, STA, link_lost, link_restored)."""
        self._callbacks.append(fn)

    async def events(self) -> AsyncIterator[RobotEvent]:
        """Async iterator over events from now on."""
        q: asyncio.Queue = asyncio.Queue()
        self._queues.append(q)
        try:
            while True:
                yield await q.get()
        finally:
            self._queues.remove(q)

    def _emit(self, kind: str, ticket: int | None = None, value: object = None, text: str = "") -> None:
        if not (self._callbacks or self._queues):
            return
        # a reply's event carries when its bytes arrived (the EXEs time the robot's pace)
        ev = RobotEvent(kind, ticket, value, text, self._rx_t or time.monotonic())
        for fn in self._callbacks:
            fn(ev)
        for q in self._queues:
            q.put_nowait(ev)

    # -- connection -----------------------------------------------------------------------------
    async def connect(self, resume_ticket: int | None = None) -> RobotStatus:
        """Open the port, ask `!STATUS`, resynchronise the next ticket from the robot's last_rx.

        `resume_ticket`: a ticket journaled earlier (e.g. the last executed one before a crash):
        the robot's 16-bit numbers are unwrapped to the tickets nearest it.
        """
        self._closing = False
        if self._connected:
            await self._drop("reconnect requested", notify=False)
        port = SerialPort(self.url, baud=self.baud, name=self.name, pace=self.pace, pace_factor=0.98 * self.line_scale)
        await port.open()
        self._port = port
        self._connected = True
        self._lost = None
        self._last_heard = self._last_tx = time.monotonic()
        self._tx_paused = True  # nothing but !STATUS until resynchronised
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._reader(port)), loop.create_task(self._sender(port)),
                       loop.create_task(self._timer())]
        try:
            st = await self._control("STATUS", lambda s: True, timeout=self.link_timeout_s)
        except (LinkLost, DeviceTimeout) as exc:
            await self._drop(str(exc), notify=False)
            raise LinkLost(f"{self.name} at {self.url}: no answer to !STATUS; is the robot on?") from None
        self._resync(st, resume_ticket)
        self._tx_paused = self.protocol_fault is not None
        self._ready = True
        self._kick.set()
        self._notify()
        if self.fault and "lost queued moves" in self.fault:
            raise DeviceError(f"{self.name} at {self.url}: {self.fault}")
        return self.last_status

    def _resync(self, st: rlp.Reply, resume_ticket: int | None) -> None:
        if resume_ticket is not None:
            rx_t = rlp.unwrap(st.last_rx, resume_ticket)
        elif self._history:
            rx_t = rlp.unwrap(st.last_rx, self._last_ack)
        else:
            rx_t = st.last_rx
        exec_t = rx_t - rlp.seq_diff(st.last_rx, st.last_exec) if rlp.seq_diff(st.last_rx, st.last_exec) >= 0 else rx_t
        self._capacity = st.queue_free + (rx_t - exec_t)
        lost_acked = self._history and rx_t < self._last_ack
        if lost_acked:  # the robot forgot moves it had acknowledged (restarted): cannot resend them
            self._frames.clear()
            self._sent_at.clear()
            self._next_ticket = rx_t + 1
            self._aborted_below = self._next_ticket
            self.fault = (f"robot reports last_rx {st.last_rx:04X} below acknowledged ticket {self._last_ack}: "
                          "it lost queued moves (restarted?); re-plan from last_exec")
        for t in [t for t in self._frames if t <= rx_t]:  # the robot has these: acknowledged
            self._frames.pop(t)
            self._sent_at.pop(t, None)
        self._retx.clear()
        self._last_ack = rx_t
        self._last_exec = exec_t
        self._next_ticket = max(self._next_ticket if self._history else 0, rx_t + 1)
        self._send_next = rx_t + 1
        self._max_sent = max(rx_t, self._send_next - 1)
        self._window_end = rx_t + st.queue_free
        self._history = True
        self._set_status(st)

    async def close(self) -> None:
        """Close the port and stop background tasks (no reconnect)."""
        self._closing = True
        if self._reconnect_task is not None:
            self._reconnect_task.cancel()
            self._reconnect_task = None
        await self._drop("closed", notify=False)

    async def _drop(self, reason: str, notify: bool = True) -> None:
        was = self._connected and self._ready  # a failed (re)connect attempt is no new loss
        self._connected = self._ready = False
        self._lost = LinkLost(f"{self.name} at {self.url}: link lost ({reason})")
        self._ctrl.clear()
        # waiters and listeners learn of the loss first: closing a socket:// port takes 0.3 s
        self._notify()
        if was and notify:
            self._emit("link_lost", text=str(self._lost))
        tasks, self._tasks = self._tasks, []
        cur = asyncio.current_task()
        for t in tasks:
            if t is not cur:
                t.cancel()
        if self._port is not None:
            port, self._port = self._port, None
            await asyncio.get_running_loop().run_in_executor(None, port.close)
        if was and notify and self.auto_reconnect and not self._closing and self._reconnect_task is None:
            self._reconnect_task = asyncio.get_running_loop().create_task(self._reconnect())

    async def _reconnect(self) -> None:
        try:
            while not self._closing:
                await asyncio.sleep(0.2)
                try:
                    st = await self.connect()
                except LinkLost:
                    continue
                except DeviceError as exc:  # connected, but the robot lost moves: the controller decides
                    self.stats.reconnects += 1
                    self._emit("link_restored", value=self.last_status, text=str(exc))
                    return
                self.stats.reconnects += 1
                self._emit("link_restored", value=st)
                return
        finally:
            self._reconnect_task = None

    async def wait_connected(self, timeout: float | None = None) -> None:
        """Wait until the link is up again (after a loss, with auto_reconnect)."""
        await self._wait(lambda: self._connected and self._ready, timeout, "reconnect", fail_on_loss=False)

    # -- motion ---------------------------------------------------------------------------------
    async def send_move(self, verb: str, *args: float, timeout: float | None = None) -> int:
        """Queue a MOVJ / MOVL / WAIT / MARK frame; returns its ticket once the robot has room."""
        body_check = rlp.move_body(0, verb, *args)  # ValueError for a malformed move, before waiting
        del body_check
        await self._wait(lambda: (self._next_ticket <= self._window_end and not self._tx_paused)
                         or self.protocol_fault is not None, timeout, "window space")
        if self.protocol_fault is not None:
            raise DeviceError(f"{self.name} at {self.url}: {self.fault}; reset() clears it")
        t = self._next_ticket
        self._next_ticket += 1
        self._frames[t] = rlp.encode_move(t, verb, *args)
        self._kick.set()
        return t

    async def wait_executed(self, ticket: int, timeout: float | None = None) -> None:
        """Return once the robot reported the move `ticket` executed (EXE, or STA last_exec).

        DeviceError when the robot faulted or the move was flushed by abort()/reset() first.
        """
        await self._wait(lambda: self._last_exec >= ticket or self.fault is not None or ticket < self._aborted_below,
                         timeout, f"execution of ticket {ticket}")
        if self._last_exec >= ticket:
            return
        if self.fault is not None:
            raise DeviceError(f"{self.name} at {self.url}: fault: {self.fault}; reset() clears it")
        raise DeviceError(f"{self.name} at {self.url}: ticket {ticket} was flushed by abort/reset, never executed")

    async def wait_acked(self, ticket: int, timeout: float | None = None) -> None:
        await self._wait(lambda: self._last_ack >= ticket, timeout, f"ACK of ticket {ticket}")

    async def drain(self, timeout: float | None = None) -> None:
        """Wait until every queued move is acknowledged by the robot."""
        await self.wait_acked(self._next_ticket - 1, timeout)

    # -- control frames ---------------------------------------------------------------------------
    async def hold(self) -> RobotStatus:
        """!HOLD: stop motion now (queue kept); returns once the robot reports HOLD."""
        return self._set_status(await self._control("HOLD", lambda s: s.state in ("HOLD", "FAULT")))

    async def go(self) -> RobotStatus:
        """!GO: release a hold or a WAIT."""
        return self._set_status(await self._control("GO", lambda s: s.state != "HOLD"))

    async def status(self) -> RobotStatus:
        return self._set_status(await self._control("STATUS", lambda s: True))

    async def abort(self) -> RobotStatus:
        """!ABORT: flush the robot's queue and drop every move not yet executed (their waiters fail)."""
        self._tx_paused = True
        try:
            self._frames.clear()
            self._sent_at.clear()
            # the robot's answer to !ABORT: queue flushed, standing still (IDLE) or faulted; its
            # free-slot count is then the whole queue (the old estimate of it may be wrong)
            st = await self._control("ABORT", lambda s: s.state in ("IDLE", "FAULT"))
            rx_t = rlp.unwrap(st.last_rx, self._last_ack)
            if st.state == "IDLE":
                self._capacity = st.queue_free
            self._last_ack = self._max_sent = rx_t
            self._next_ticket = self._send_next = rx_t + 1
            self._last_exec = rx_t - rlp.seq_diff(st.last_rx, st.last_exec)
            self._window_end = rx_t + st.queue_free
            self._aborted_below = self._next_ticket
            self._set_status(st)
        finally:
            self._tx_paused = self.protocol_fault is not None
            self._notify()
        return self.last_status

    async def reset(self) -> RobotStatus:
        """!RESET: clear the robot's queue and fault; the next ticket maps to seq 0001."""
        self._tx_paused = True
        try:
            self._frames.clear()
            self._sent_at.clear()
            st = await self._control("RESET", lambda s: s.last_rx == 0 and s.last_exec == 0
                                     and s.state == "IDLE")
            self._capacity = st.queue_free
            base = (self._next_ticket - 1) | 0xFFFF  # the next ticket whose low 16 bits are 0000
            self._last_ack = self._last_exec = self._max_sent = base + 1
            self._next_ticket = self._send_next = base + 2
            self._window_end = base + 1 + st.queue_free
            self.fault = None
            self.protocol_fault = None
            self._aborted_below = self._next_ticket
            self.last_status = RobotStatus(st.state, 0, 0, st.queue_free, st.pos, base + 1, base + 1)
        finally:
            self._tx_paused = False
            self._notify()
        return self.last_status

    async def _control(self, verb: str, done: Callable[[rlp.Reply], bool], timeout: float | None = None) -> rlp.Reply:
        """Send `!VERB` ahead of the queue, resend it until a STA satisfying `done` arrives."""
        timeout = self.link_timeout_s if timeout is None else timeout
        frame = rlp.encode("!" + verb)
        deadline = time.monotonic() + timeout
        async with self._ctrl_lock:
            while True:
                if not self._connected:
                    raise self._lost or LinkLost(f"{self.name} at {self.url}: not connected")
                self._sta_seen = None
                self._ctrl.append(frame)
                self._kick.set()
                wait = min(max(self.control_timeout_s, 4 * (self._srtt or 0.0)), deadline - time.monotonic())
                try:
                    await self._wait(lambda: self._sta_seen is not None and done(self._sta_seen), max(wait, 0.001),
                                     f"!{verb}")
                    return self._sta_seen
                except DeviceTimeout:
                    if time.monotonic() >= deadline:
                        raise DeviceTimeout(f"{self.name} at {self.url}: no answer to !{verb} within {timeout:.1f} s") from None

    def _set_status(self, st: rlp.Reply) -> RobotStatus:
        rx_t = rlp.unwrap(st.last_rx, self._last_ack)
        d = rlp.seq_diff(st.last_rx, st.last_exec)
        exec_t = rx_t - d if d >= 0 else rx_t
        self.last_status = RobotStatus(st.state, st.last_rx, st.last_exec, st.queue_free, st.pos, rx_t, exec_t)
        return self.last_status

    # -- waiting ------------------------------------------------------------------------------------
    def _notify(self) -> None:
        ev, self._change = self._change, asyncio.Event()
        ev.set()

    async def _wait(self, pred: Callable[[], bool], timeout: float | None, what: str, fail_on_loss: bool = True) -> None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not pred():
            if fail_on_loss and not self._connected:
                raise self._lost or LinkLost(f"{self.name} at {self.url}: not connected")
            ev = self._change
            if deadline is None:
                await ev.wait()
            else:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceTimeout(f"{self.name} at {self.url}: timed out waiting for {what}")
                try:
                    await asyncio.wait_for(ev.wait(), left)
                except asyncio.TimeoutError:
                    raise DeviceTimeout(f"{self.name} at {self.url}: timed out waiting for {what}") from None

    # -- background tasks --------------------------------------------------------------------------
    async def _sender(self, port: SerialPort) -> None:
        try:
            while True:
                await self._kick.wait()
                self._kick.clear()
                while self._connected:
                    t = None
                    if self._ctrl:
                        data = self._ctrl.popleft()
                    else:
                        t = self._send_next
                        if (self._tx_paused or t >= self._next_ticket or t > self._window_end
                                or (self.max_inflight and t - self._last_ack > self.max_inflight)):
                            break
                        data = self._frames[t]
                        if t in self._sent_at:
                            self.stats.resends += 1
                            self._retx.add(t)
                        self._sent_at[t] = time.monotonic()
                        self._send_next = t + 1
                        self._max_sent = max(self._max_sent, t)
                    await port.write(data)  # waits for the line (pacing)
                    self._last_tx = time.monotonic()
                    if t is None and data == _HOLD_FRAME:
                        self.hold_tx.append(self._last_tx)
                    if t is not None and t in self._frames:
                        self._sent_at[t] = self._last_tx  # on the wire now: the RTT starts here
                    self.stats.frames_sent += 1
                    self.stats.bytes_sent += len(data)
        except LinkLost as exc:
            if self._port is port:
                await self._drop(getattr(exc, "reason", str(exc)))

    async def _reader(self, port: SerialPort) -> None:
        splitter = rlp.LineSplitter()
        try:
            while True:
                data = await port.read()
                self._rx_t = port.rx_t
                self.stats.bytes_received += len(data)
                # bounded per read: the build's own frames first, a few heartbeats after
                own, hb = split_lines(splitter.feed(data))
                for line in own[:MAX_OWN_PER_READ]:
                    self._on_line(line)
                self.stats.bad_frames += max(0, len(own) - MAX_OWN_PER_READ)
                for line in hb[:MAX_HB_PER_READ]:
                    self._on_line(line)
                self.stats.heartbeats += len(hb)
                self.stats.hb_skipped += max(0, len(hb) - MAX_HB_PER_READ)
                if self._flood.add(len(hb)) and self.protocol_fault is None:
                    self._protocol(f"heartbeat flood: {self._flood.rate} HB frames within 1 s (expected 1/s)")
                self._rx_t = None
                self._notify()
                self._kick.set()
                if len(own) + len(hb) > MAX_HB_PER_READ:
                    await asyncio.sleep(0)  # a busy line leaves the other tasks their turn
        except LinkLost as exc:
            if self._port is port:
                await self._drop(getattr(exc, "reason", str(exc)))

    async def _timer(self) -> None:
        while self._connected:
            await asyncio.sleep(self.TICK_S)
            now = time.monotonic()
            if (now - self._last_heard >= SUSPECT_S and not self._suspect_held
                    and self._last_exec < self._next_ticket - 1):
                # quiet for a second with moves outstanding: hold the robot now (it may still
                # hear us and it must not go on depositing blind); lost at link_timeout_s
                self._suspect_held = True
                self.held_at = now
                self._ctrl.appendleft(rlp.encode("!HOLD"))
                self._kick.set()
            if now - self._last_heard >= self.link_timeout_s - self.TICK_S:  # lost within link_timeout_s
                # no valid frame for 3 s (silent, or only garbage / floods): hold the robot first,
                # it may still hear us
                port = self._port
                if port is not None:
                    try:
                        await asyncio.wait_for(port.write(rlp.encode("!HOLD")), 0.1)
                        await asyncio.sleep(0.05)  # on the line before the port closes
                    except Exception:
                        pass
                await self._drop(f"no valid frame for {self.link_timeout_s:.1f} s")
                return
            oldest = self._last_ack + 1
            sent = self._sent_at.get(oldest)
            if sent is not None and oldest < self._send_next and now - sent > self._rto:
                self.stats.timeouts += 1
                self._send_next = oldest  # go back to the oldest unacknowledged frame
                self._rto = min(2 * self._rto, self.rto_max_s)
                self._kick.set()
            if now - self._last_tx > self.keepalive_s and not self._ctrl:
                # keeps the robot's silence watchdog fed and refreshes a closed window
                self._ctrl.append(rlp.encode("!STATUS"))
                self._last_tx = now
                self._kick.set()

    # -- receiving ----------------------------------------------------------------------------------
    def _rtt_sample(self, r: float) -> None:
        self.stats.rtt_s.append(r)
        self._min_rtt = r if self._min_rtt is None else min(self._min_rtt, r)
        if self._srtt is None:
            self._srtt, self._rttvar = r, r / 2
        else:
            self._rttvar = 0.75 * self._rttvar + 0.25 * abs(self._srtt - r)
            self._srtt = 0.875 * self._srtt + 0.125 * r
        self._rto = min(max(self._srtt + 4 * self._rttvar, self.rto_min_s), self.rto_max_s)

    def _acked(self, a: int) -> None:
        """Everything up to ticket `a` is received by the robot."""
        if a <= self._last_ack or a >= self._next_ticket:
            return
        sent = self._sent_at.get(a)
        if sent is not None and a not in self._retx:
            self._rtt_sample(time.monotonic() - sent)
        for t in range(self._last_ack + 1, a + 1):
            self._frames.pop(t, None)
            self._sent_at.pop(t, None)
            self._retx.discard(t)
        self._last_ack = a
        if self._send_next <= a:
            self._send_next = a + 1

    def _on_line(self, line: bytes) -> None:
        r = self._decode(line)
        if r is None:
            return
        if r.kind != "HB":
            if not self._plausible(r):
                return
            self._last_heard = time.monotonic()  # heard: a valid frame that fits what was sent
            if self._suspect_held and self.protocol_fault is None:
                self._suspect_held = False  # it speaks again: release the hold we wrote
                self._ctrl.append(rlp.encode("!GO"))
        handler = getattr(self, f"_on_{r.kind.lower()}", None)
        if handler is not None:
            handler(r)

    def _decode(self, line: bytes) -> rlp.Reply | None:
        """The reply in a line, or None (counted; a run of bad frames is a protocol fault)."""
        try:
            r = rlp.parse_reply(rlp.decode(line))
        except rlp.FrameError as exc:
            if exc.reason == "CRC":
                self.stats.crc_errors += 1
            else:
                self.stats.bad_frames += 1
            self._bad_run += 1
            if self._bad_run >= GARBLED_RUN and self.protocol_fault is None:
                self._protocol(f"{self._bad_run} bad frames in a row (garbled replies)")
            return None
        self._bad_run = 0
        self.stats.frames_received += 1
        return r

    def _on_ack(self, r: rlp.Reply) -> None:
        a = rlp.unwrap(r.seq, self._last_ack)
        self._bad_at_ack = self.stats.crc_errors + self.stats.bad_frames
        self._acked(a)
        if a >= self._last_ack:
            self._window_end = max(self._window_end, a + r.credits)

    def _on_exe(self, r: rlp.Reply) -> None:
        self._executed(rlp.unwrap(r.seq, self._last_exec))

    def _on_nak(self, r: rlp.Reply) -> None:
        self.stats.naks += 1
        self.stats.naks_by_reason[r.reason] = self.stats.naks_by_reason.get(r.reason, 0) + 1
        x = rlp.unwrap(r.seq, self._last_ack + 1)
        self._acked(x - 1)  # the robot expects x: it has everything before
        if r.reason == "FULL":
            self._window_end = min(self._window_end, x - 1)
        sent = self._sent_at.get(x)
        # a NAK sooner than a round trip after x's last transmission is about an earlier one
        fresh = sent is None or self._min_rtt is None or time.monotonic() - sent >= 0.7 * self._min_rtt
        if x == self._last_ack + 1 and x < self._send_next and fresh:
            self._send_next = x
            self._kick.set()

    def _on_sta(self, r: rlp.Reply) -> None:
        self._sta_seen = r
        rx_t = rlp.unwrap(r.last_rx, self._last_ack)
        if not self._tx_paused:
            self._acked(rx_t)
            self._window_end = max(self._window_end, rx_t + r.queue_free)
            d = rlp.seq_diff(r.last_rx, r.last_exec)
            if d >= 0:
                self._executed(rx_t - d)
        self._emit("STA", value=r)

    def _on_hb(self, r: rlp.Reply) -> None:
        self._emit("HB", value=r.n)

    def _on_mrk(self, r: rlp.Reply) -> None:
        self._emit("MRK", value=r.n)

    def _on_err(self, r: rlp.Reply) -> None:
        self.fault = f"ERR {r.code} {r.text}"
        self._emit("ERR", value=r.code, text=r.text)

    def _plausible(self, r: rlp.Reply) -> bool:
        """False (and a latched protocol fault) for an ACK / EXE the host cannot have caused."""
        if r.kind == "ACK":
            a = rlp.unwrap(r.seq, self._last_ack)
            if a > self._max_sent:
                self._protocol(f"ACK {r.seq:04X} for ticket {a}, never sent (last sent {self._max_sent})")
                return False
        elif r.kind == "EXE":
            e = rlp.unwrap(r.seq, self._last_exec)
            if e > self._max_sent:
                self._protocol(f"EXE {r.seq:04X} for ticket {e}, never sent (last sent {self._max_sent})")
                return False
            if e < self._last_exec and not self._tx_paused:
                self._protocol(f"EXE {r.seq:04X} out of order (ticket {e} after {self._last_exec})")
                return False
            lost = self.stats.crc_errors + self.stats.bad_frames > self._bad_at_ack
            if e > self._last_ack and not lost and not self._tx_paused:
                self._protocol(f"EXE {r.seq:04X} (ticket {e}) beyond the last ACK ({self._last_ack})")
                return False
        return True

    def _protocol(self, text: str) -> None:
        """Latch a protocol fault: no more moves, `!HOLD` at once, tell the controller (ERR)."""
        self.stats.protocol_faults += 1
        if self.protocol_fault is not None:
            return
        self.protocol_fault = text
        self.fault = f"protocol fault: {text}"
        self._tx_paused = True
        self.held_at = time.monotonic()
        self._ctrl.appendleft(rlp.encode("!HOLD"))
        self._kick.set()
        self._notify()
        self._emit("ERR", value="PROTOCOL", text=f"protocol fault: {text}")

    def _executed(self, e: int) -> None:
        if e <= self._last_exec or e >= self._next_ticket:
            return
        emit = self._callbacks or self._queues
        first = self._last_exec + 1
        self._last_exec = e
        self._window_end = max(self._window_end, e + self._capacity)
        if emit:
            for t in range(first, e + 1):
                self._emit("EXE", ticket=t)

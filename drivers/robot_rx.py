"""The state of the robot link and its receiving half (drivers/robot.py's RobotLink): the reader
task and what each robot frame does to the window, the events and the liveness."""
from __future__ import annotations

import asyncio
import time
from collections import deque
from typing import AsyncIterator, Callable

from wire import rlp
from drivers.errors import LinkLost
from drivers.liveness import LinkLiveness
from drivers.rlp_hello import Hello
from drivers.rlp_window import RtoEstimator, TicketWindow
from drivers.robot_guard import GARBLED_RUN, SUSPECT_S, FloodMeter
from drivers.robot_records import (Ack, Err, EventHub, Exe, Hb, LinkStats, Mrk, Nak, Proto, Reply, RobotEvent, RobotStatus,
                                   Sack, Sta, decode_reply)
from drivers.serial_async import SerialPort
from drivers.waiting import Changes

HOLD_FRAME = rlp.encode("!HOLD")


class RobotLinkState(LinkLiveness[LinkStats]):
    """What the robot link knows (shared by its sending and receiving halves) and the receiving half."""

    TICK_S = 0.02  # retransmit / link-loss / keepalive check period
    # retransmission timeout bounds per protocol: RLP/1 as specified; RLP/2 resends a frame alone,
    # so a short timeout costs one frame, not the window (Klipper's 25 ms - 5 s)
    RTO_BOUNDS = {1: (0.1, 1.0), 2: (0.025, 5.0)}

    def __init__(self, url: str, *, baud: int = 115200, link_timeout_s: float = 3.0, name: str = "robot",
                 pace: bool = True, max_inflight: int | None = None, auto_reconnect: bool = True,
                 keepalive_s: float = 0.5, control_timeout_s: float = 0.25,
                 rto_min_s: float | None = None, rto_max_s: float | None = None, line_scale: float = 1.0,
                 max_protocol: int = 2) -> None:
        super().__init__(LinkStats(), lost_after_s=link_timeout_s, late_after_s=min(SUSPECT_S, link_timeout_s))
        self.url = url
        self.baud = baud
        # a simulated line at time scale k carries k times the bytes per wall second (docs/contract.md §6):
        # pace the writes at that rate, or the host, not the line, starves the bead
        self.line_scale = line_scale
        self.name = name
        self.pace = pace
        self.max_inflight = max_inflight   # 1: send-and-wait (the benchmark's baseline)
        self.auto_reconnect = auto_reconnect
        self.keepalive_s = keepalive_s
        self.control_timeout_s = control_timeout_s
        self.last_status: RobotStatus | None = None
        self.fault: str | None = None
        # RLP/2 (selective repeat) when the robot speaks it, else RLP/1 (docs/protocols/rlp.md §9)
        self.max_protocol = max_protocol
        self._rto_bounds = (rto_min_s, rto_max_s)   # None: the protocol's own (RTO_BOUNDS)
        self._hello = Hello()
        self._w = TicketWindow(RtoEstimator(*self._bounds(1), self.stats.rtt_s))
        self._rx_t: float | None = None     # arrival time of the chunk being parsed
        self._port: SerialPort | None = None
        self._connected = False
        self._ready = False                # connected and resynchronised
        self._closing = False
        self._ctrl: deque[bytes] = deque()
        self._tx_paused = False
        self._last_tx = 0.0
        self._kick = asyncio.Event()
        self._changes = Changes(f"{name} at {url}")
        self._tasks: list[asyncio.Task[None]] = []
        self._reconnect_task: asyncio.Task[None] | None = None
        self._ctrl_lock = asyncio.Lock()
        self._events = EventHub()
        self._lost: LinkLost | None = None
        self._sta_seen: Sta | None = None
        self._bad_at_ack = 0               # bad frames received up to the last ACK
        self._flood = FloodMeter()
        self.protocol_fault: str | None = None  # latched: holds motion until reset()
        self._suspect_held = False         # we wrote !HOLD because the robot went quiet
        self.held_at: float | None = None  # monotonic time the link itself last wrote !HOLD
        # when !HOLD frames actually went out on the line (a bead cut blind is timed to the first)
        self.hold_tx: deque[float] = deque(maxlen=16)


    # -- events ---------------------------------------------------------------------------------
    def on_event(self, fn: Callable[[RobotEvent], None]) -> None:
        """Call `fn(event)` for every event (EXE, MRK, ERR, HB, STA, link_lost, link_restored)."""
        self._events.add(fn)

    def events(self) -> AsyncIterator[RobotEvent]:
        """Async iterator over events from now on."""
        return self._events.stream()

    def _emit(self, kind: str, ticket: int | None = None, value: object = None, text: str = "") -> None:
        if self._events.listening:
            # a reply's event carries when its bytes arrived (the EXEs time the robot's pace)
            self._events.emit(RobotEvent(kind, ticket, value, text, self._rx_t or time.monotonic()))


    @property
    def protocol(self) -> int:
        """The RLP version in force: 2 (selective repeat) or 1 (go-back-N)."""
        return 2 if self._w.selective else 1

    def _bounds(self, version: int) -> tuple[float, float]:
        lo, hi = self.RTO_BOUNDS[version]
        return (self._rto_bounds[0] or lo, self._rto_bounds[1] or hi)

    # -- receiving ----------------------------------------------------------------------------------
    def _on_line(self, line: bytes) -> None:
        r = self._decode(line)
        if r is None:
            return
        if not isinstance(r, Hb):
            fault = self._w.implausible(r, frames_lost=self.stats.crc_errors + self.stats.bad_frames > self._bad_at_ack,
                                        paused=self._tx_paused)
            if fault is not None:
                if isinstance(r, Exe) and self._w.retract(rlp.unwrap(r.seq, self._w.last_exec)):
                    self._emit("RETRACT", ticket=self._w.last_exec)  # a lie taken back (RlpWindow.retract)
                self._protocol(fault)
                return
            self._heard()  # heard: a valid frame that fits what was sent
            if self._suspect_held and self.protocol_fault is None:
                self._suspect_held = False  # it speaks again: release the hold we wrote
                self._ctrl.append(rlp.encode("!GO"))
        self._dispatch(r)

    def _dispatch(self, r: Reply) -> None:
        now = time.monotonic()
        if isinstance(r, (Ack, Sack)):
            self._bad_at_ack = self.stats.crc_errors + self.stats.bad_frames
            self.stats.sacks += isinstance(r, Sack)
            if self._w.on_ack(r, now):  # RLP/2: frames found lost are sent again at once
                self._kick.set()
        elif isinstance(r, Exe):
            self._executed(self._w.executed(rlp.unwrap(r.seq, self._w.last_exec)))
        elif isinstance(r, Nak):
            self._hello.on_nak(r.reason)
            self.stats.naks += 1
            self.stats.naks_by_reason[r.reason] = self.stats.naks_by_reason.get(r.reason, 0) + 1
            if self._w.on_nak(r.seq, r.reason, now):
                self._kick.set()
        elif isinstance(r, Sta):
            self._sta_seen = r
            if not self._tx_paused:
                self._executed(self._w.on_sta(r, now))
            self._emit("STA", value=r)
        elif isinstance(r, Hb):
            self._emit("HB", value=r.n)
        elif isinstance(r, Proto):
            self._hello.on_proto(r.version)
        elif isinstance(r, Mrk):
            self._emit("MRK", value=r.n)
        elif isinstance(r, Err):
            self.fault = f"ERR {r.code} {r.text}"
            self._emit("ERR", value=r.code, text=r.text)

    def _decode(self, line: bytes) -> Reply | None:
        """The reply in a line, or None (counted; a run of bad frames is a protocol fault)."""
        try:
            r = decode_reply(line)
        except rlp.FrameError as exc:
            if exc.reason == "CRC":
                self.stats.crc_errors += 1
            else:
                self.stats.bad_frames += 1
            run = self._bad()
            if run >= GARBLED_RUN and self.protocol_fault is None:
                self._protocol(f"{run} bad frames in a row (garbled replies)")
            return None
        self._valid()
        self.stats.frames_received += 1
        return r

    def _protocol(self, text: str) -> None:
        """Latch a protocol fault: no more moves, `!HOLD` at once, tell the controller (ERR)."""
        self.stats.protocol_faults += 1
        if self.protocol_fault is not None:
            return
        self.protocol_fault = text
        self.fault = f"protocol fault: {text}"
        self._tx_paused = True
        self.held_at = time.monotonic()
        self._ctrl.appendleft(HOLD_FRAME)
        self._kick.set()
        self._changes.notify()
        self._emit("ERR", value="PROTOCOL", text=f"protocol fault: {text}")

    def _executed(self, tickets: range) -> None:
        """Report the newly executed tickets (EXE events)."""
        if tickets and self._events.listening:
            for t in tickets:
                self._emit("EXE", ticket=t)

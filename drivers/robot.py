"""RobotLink: the asyncio host side of RLP/1 and RLP/2 (docs/contract.md §5, docs/protocols/rlp.md).

Moves are numbered with *tickets*: unwrapped, monotonically increasing ints whose low 16 bits
are the wire sequence number, so a job of any length is journaled unambiguously. The link keeps
a sliding window bounded by the robot's queue (credits), takes cumulative ACKs, negotiates the
protocol at connect (`!PROTO 2`): with an RLP/2 robot it sends again only the frames lost
(selective repeat, drivers/rlp_window.py), with an RLP/1 robot it goes back to the NAKed frame
(go-back-N); it retransmits on an adaptive timeout (Jacobson/Karn), sends control frames ahead of the queue, watches the
heartbeat (link lost after `link_timeout_s` of silence or when the port closes), and after a
reconnect resynchronises from the robot's last received / last executed sequence numbers.

Usage: `open_robot(cfg)` (drivers/registry.py), `connect(resume_ticket=...)`, `send_move(...)`, `wait_executed(ticket)`.
Waiters get LinkLost (naming device and URL) when the link drops; auto_reconnect emits `link_restored` (held stays held).
"""
from __future__ import annotations

import asyncio
import time
from typing import Callable

from wire import rlp
from drivers.errors import DeviceError, DeviceTimeout, LinkLost
from drivers.rlp_hello import negotiate
from drivers.robot_guard import MAX_HB_PER_READ, MAX_OWN_PER_READ, split_lines
from drivers.robot_records import LinkStats, RobotEvent, RobotStatus, Sta
from drivers.robot_rx import HOLD_FRAME, RobotLinkState
from drivers.serial_async import SerialPort

__all__ = ["LinkStats", "RobotEvent", "RobotLink", "RobotStatus"]  # its records are part of its interface (ports.py)


class RobotLink(RobotLinkState):
    """The robot link driver, all coroutines on one loop; heard / late (SUSPECT_S) / lost (`link_timeout_s`) by LinkLiveness.
    Constructor: drivers/robot_rx.py (RobotLinkState)."""

    @property
    def max_sent(self) -> int:
        """The highest ticket ever transmitted (the last weld move the robot can have executed)."""
        return self._w.max_sent

    @property
    def link_timeout_s(self) -> float:  # lost after this long without a valid frame (LinkLiveness)
        return self.lost_after_s

    @property
    def connected(self) -> bool:
        """True once connect() has resynchronised, until the link is lost."""
        return self._connected and self._ready

    @property
    def last_exec_ticket(self) -> int:
        return self._w.last_exec

    @property
    def last_ack_ticket(self) -> int:
        return self._w.last_ack

    @property
    def queue_capacity(self) -> int:
        """The robot's queue size as learned at connect (0 before): a flushed queue has this many free."""
        return self._w.capacity

    @property
    def next_ticket(self) -> int:
        return self._w.next_ticket

    @property
    def rto_s(self) -> float:
        return self._w.rtt.rto

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
        self._link_up()
        self._last_tx = time.monotonic()
        self._tx_paused = True  # nothing but !STATUS until resynchronised
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._reader(port)), loop.create_task(self._sender(port)),
                       loop.create_task(self._timer())]
        try:
            st = await self._control("STATUS", lambda s: True, timeout=self.link_timeout_s)
        except (LinkLost, DeviceTimeout) as exc:
            await self._drop(str(exc), notify=False)
            raise LinkLost(f"{self.name} at {self.url}: no answer to !STATUS; is the robot on?") from None
        lost_moves = self._w.resync(st, resume_ticket)
        if lost_moves is not None:
            self.fault = lost_moves
        status = self._set_status(st)
        await self._negotiate()
        self._tx_paused = self.protocol_fault is not None
        self._ready = True
        self._kick.set()
        self._changes.notify()
        if self.fault and "lost queued moves" in self.fault:
            raise DeviceError(f"{self.name} at {self.url}: {self.fault}")
        return status

    async def _negotiate(self) -> None:
        def send(frame: bytes) -> None:
            self._ctrl.append(frame)
            self._kick.set()

        async def wait(pred: Callable[[], bool], timeout: float) -> None:
            await self._wait(pred, timeout, "!PROTO")

        version = await negotiate(self._hello, self.max_protocol, send, wait,
                                  max(self.control_timeout_s, 4 * (self._w.rtt.srtt or 0.0)))
        self._w.selective = version >= 2
        self._w.rtt.rto_min_s, self._w.rtt.rto_max_s = self._bounds(version)
        self.stats.protocol = version

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
        self._lost = LinkLost(f"{self.name} at {self.url}: link lost ({reason})", reason=reason)
        self._ctrl.clear()
        # waiters and listeners learn of the loss first: closing a socket:// port takes 0.3 s
        self._changes.notify()
        if was and notify:
            self._count_lost()
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
        rlp.move_body(0, verb, *args)  # ValueError for a malformed move, before waiting
        await self._wait(lambda: (self._w.has_room() and not self._tx_paused) or self.protocol_fault is not None,
                         timeout, "window space")
        if self.protocol_fault is not None:
            raise DeviceError(f"{self.name} at {self.url}: {self.fault}; reset() clears it")
        t = self._w.queue(rlp.encode_move(self._w.next_ticket, verb, *args))
        self._kick.set()
        return t

    async def wait_executed(self, ticket: int, timeout: float | None = None) -> None:
        """Return once the robot reported the move `ticket` executed (EXE, or STA last_exec).

        DeviceError when the robot faulted or the move was flushed by abort()/reset() first.
        """
        w = self._w
        await self._wait(lambda: w.last_exec >= ticket or self.fault is not None or ticket < w.aborted_below,
                         timeout, f"execution of ticket {ticket}")
        if w.last_exec >= ticket:
            return
        if self.fault is not None:
            raise DeviceError(f"{self.name} at {self.url}: fault: {self.fault}; reset() clears it")
        raise DeviceError(f"{self.name} at {self.url}: ticket {ticket} was flushed by abort/reset, never executed")

    async def wait_acked(self, ticket: int, timeout: float | None = None) -> None:
        await self._wait(lambda: self._w.last_ack >= ticket, timeout, f"ACK of ticket {ticket}")

    async def drain(self, timeout: float | None = None) -> None:
        """Wait until every queued move is acknowledged by the robot."""
        await self.wait_acked(self._w.next_ticket - 1, timeout)

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
            self._w.forget_frames()
            # the robot's answer to !ABORT: queue flushed, standing still (IDLE) or faulted
            st = await self._control("ABORT", lambda s: s.state in ("IDLE", "FAULT"))
            self.last_status = status = self._w.after_abort(st)
        finally:
            self._tx_paused = self.protocol_fault is not None
            self._changes.notify()
        return status

    async def reset(self) -> RobotStatus:
        """!RESET: clear the robot's queue and fault; the next ticket maps to seq 0001."""
        self._tx_paused = True
        try:
            self._w.forget_frames()
            st = await self._control("RESET", lambda s: s.last_rx == 0 and s.last_exec == 0
                                     and s.state == "IDLE")
            self.last_status = status = self._w.after_reset(st)
            self.fault = None
            self.protocol_fault = None
        finally:
            self._tx_paused = False
            self._changes.notify()
        return status

    async def _control(self, verb: str, done: Callable[[Sta], bool], timeout: float | None = None) -> Sta:
        """Send `!VERB` ahead of the queue, resend it until a STA satisfying `done` arrives."""
        timeout = self.link_timeout_s if timeout is None else timeout
        frame = rlp.encode("!" + verb)
        deadline = time.monotonic() + timeout
        async with self._ctrl_lock:
            while True:
                self._check_up()
                self._sta_seen = None
                self._ctrl.append(frame)
                self._kick.set()
                wait = min(max(self.control_timeout_s, 4 * (self._w.rtt.srtt or 0.0)), deadline - time.monotonic())
                try:
                    await self._wait(lambda: self._sta_seen is not None and done(self._sta_seen), max(wait, 0.001),
                                     f"!{verb}")
                except DeviceTimeout:
                    if time.monotonic() >= deadline:
                        raise DeviceTimeout(f"{self.name} at {self.url}: no answer to !{verb} within {timeout:.1f} s") from None
                    continue
                st = self._sta_seen
                if st is not None:  # always: _wait returned on it, with no await in between
                    return st

    def _set_status(self, st: Sta) -> RobotStatus:
        self.last_status = self._w.status(st)
        return self.last_status

    # -- waiting ------------------------------------------------------------------------------------
    def _check_up(self) -> None:
        if not self._connected:
            raise self._lost or LinkLost(f"{self.name} at {self.url}: not connected")

    async def _wait(self, pred: Callable[[], bool], timeout: float | None, what: str, fail_on_loss: bool = True) -> None:
        await self._changes.until(pred, timeout, what, self._check_up if fail_on_loss else None)

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
                        nxt = None if self._tx_paused else self._w.take_next(self.max_inflight, time.monotonic())
                        if nxt is None:
                            break
                        t, data, resend = nxt
                        self.stats.resends += resend
                    await port.write(data)  # waits for the line (pacing)
                    self._last_tx = time.monotonic()
                    if t is None and data == HOLD_FRAME:
                        self.hold_tx.append(self._last_tx)
                    if t is not None:
                        self._w.on_wire(t, self._last_tx)  # on the wire now: the RTT starts here
                    self.stats.frames_sent += 1
                    self.stats.bytes_sent += len(data)
        except LinkLost as exc:
            if self._port is port:
                await self._drop(exc.reason)

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
                over = max(0, len(own) - MAX_OWN_PER_READ)
                self.stats.bad_frames += over
                self.stats.bad += over
                for line in hb[:MAX_HB_PER_READ]:
                    self._on_line(line)
                self.stats.heartbeats += len(hb)
                self.stats.hb_skipped += max(0, len(hb) - MAX_HB_PER_READ)
                if self._flood.add(len(hb)) and self.protocol_fault is None:
                    self._protocol(f"heartbeat flood: {self._flood.rate} HB frames within 1 s (expected 1/s)")
                self._rx_t = None
                self._changes.notify()
                self._kick.set()
                if len(own) + len(hb) > MAX_HB_PER_READ:
                    await asyncio.sleep(0)  # a busy line leaves the other tasks their turn
        except LinkLost as exc:
            if self._port is port:
                await self._drop(exc.reason)


    async def _timer(self) -> None:
        while self._connected:
            await asyncio.sleep(self.TICK_S)
            now = time.monotonic()
            if self._quiet(now) and not self._suspect_held and self._w.outstanding():
                # quiet for a while with moves outstanding: hold the robot now (it may still
                # hear us and it must not go on depositing blind); lost at link_timeout_s
                self._suspect_held = True
                self.held_at = now
                self._ctrl.appendleft(HOLD_FRAME)
                self._kick.set()
            if self._lost_due(now, margin_s=self.TICK_S):  # lost within link_timeout_s
                await self._lost_silent()
                return
            if self._w.retransmit_due(now):  # go back to the oldest unacknowledged frame
                self.stats.timeouts += 1
                self._kick.set()
            if now - self._last_tx > self.keepalive_s and not self._ctrl:
                # keeps the robot's silence watchdog fed and refreshes a closed window
                self._ctrl.append(rlp.encode("!STATUS"))
                self._last_tx = now
                self._kick.set()

    async def _lost_silent(self) -> None:
        """No valid frame for link_timeout_s (silent, or only garbage / floods): hold the robot
        first, it may still hear us; then drop the link."""
        port = self._port
        if port is not None:
            try:
                await asyncio.wait_for(port.write(HOLD_FRAME), 0.1)
                await asyncio.sleep(0.05)  # on the line before the port closes
            except Exception:  # the port may be gone already: the drop follows either way
                pass
        await self._drop(f"no valid frame for {self.link_timeout_s:.1f} s")


"""The frame and queue bookkeeping of the RLP/1 host (drivers/robot.py): tickets, the sliding
window, acknowledgements, execution, retransmission and the adaptive timeout. No I/O, no tasks:
`RobotLink` calls it from its sender, reader and timer, all on one event loop.

Tickets are unwrapped, monotonically increasing ints whose low 16 bits are the wire sequence
number. The window is bounded by the robot's queue (credits); ACKs are cumulative.

RLP/1 (`selective` False): a NAK goes back to the NAKed frame at once (go-back-N: the robot
discards what follows a bad frame); a frame unacknowledged after the retransmission timeout
(Jacobson/Karn) is sent again with everything after it.

RLP/2 (`selective` True, docs/protocols/rlp.md §9): the robot keeps frames that arrive beyond a
gap and says so (SACK). Only the missing frames are sent again: a gap below a frame the robot
holds whose copies all left before that frame's first copy is lost (the line keeps the order of
bytes), a NAK names the lowest gap, and each frame has its own retransmission timeout. Frames
the robot holds stay in `frames` until the cumulative ACK covers them (a SACK is advice: a robot
that forgets them, e.g. after a reconnect, gets them again).
"""
from __future__ import annotations

from collections import deque

from drivers.robot_records import Ack, Exe, Reply, RobotStatus, Sack, Sta
from wire import rlp


class RtoEstimator:
    """Round-trip time and retransmission timeout (Jacobson's smoothing, clamped)."""

    def __init__(self, rto_min_s: float, rto_max_s: float, log: deque[float]) -> None:
        self.rto_min_s, self.rto_max_s = rto_min_s, rto_max_s
        self.log = log                    # every sample, for the link statistics
        self.srtt: float | None = None
        self.rttvar = 0.0
        self.rto = 0.25
        self.min_rtt: float | None = None

    def sample(self, r: float) -> None:
        self.log.append(r)
        self.min_rtt = r if self.min_rtt is None else min(self.min_rtt, r)
        if self.srtt is None:
            self.srtt, self.rttvar = r, r / 2
        else:
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(self.srtt - r)
            self.srtt = 0.875 * self.srtt + 0.125 * r
        self.rto = min(max(self.srtt + 4 * self.rttvar, self.rto_min_s), self.rto_max_s)

    def back_off(self) -> None:
        self.rto = min(2 * self.rto, self.rto_max_s)


class TicketWindow:
    """The host's view of the robot's queue: what is queued, sent, acknowledged and executed."""

    def __init__(self, rtt: RtoEstimator) -> None:
        self.rtt = rtt
        self.history = False              # tickets already assigned in this session
        self.next_ticket = 1              # the ticket queue() assigns next
        self.send_next = 1                # the ticket the sender transmits next
        self.last_ack = 0
        self.last_exec = 0
        self.window_end = 0               # highest ticket the robot's queue can take now
        self.capacity = 0
        self.frames: dict[int, bytes] = {}
        self.sent_at: dict[int, float] = {}
        self.retx: set[int] = set()
        self.aborted_below = 0            # tickets below this and not executed were flushed
        self.max_sent = 0                 # highest ticket ever transmitted (an ACK/EXE above: a lie)
        # RLP/2, selective repeat
        self.selective = False
        self.sacked: set[int] = set()     # held by the robot beyond the cumulative ACK (its last SACK)
        self.resend: set[int] = set()     # found lost: sent again before any new frame
        self._serial = 0                  # transmissions so far (the line's order)
        self.first_tx: dict[int, int] = {}
        self.last_tx: dict[int, int] = {}

    # -- queueing and sending -------------------------------------------------------------------
    def has_room(self) -> bool:
        return self.next_ticket <= self.window_end

    def outstanding(self) -> bool:
        """Moves queued that the robot has not reported executed."""
        return self.last_exec < self.next_ticket - 1

    def queue(self, frame: bytes) -> int:
        """Queue an encoded move frame under the next ticket (its seq must be that ticket's)."""
        t = self.next_ticket
        self.next_ticket += 1
        self.frames[t] = frame
        return t

    def take_next(self, max_inflight: int | None, now: float) -> tuple[int, bytes, bool] | None:
        """(ticket, frame, is a resend) to transmit now, or None when the window allows none."""
        if self.resend:
            lost = self._take_lost(now)
            if lost is not None:
                return lost
        t = self.send_next
        if t >= self.next_ticket or t > self.window_end or (max_inflight and t - self.last_ack > max_inflight):
            return None
        resend = t in self.sent_at
        if resend:
            self.retx.add(t)
        self._stamp(t, now)
        self.send_next = t + 1
        self.max_sent = max(self.max_sent, t)
        return t, self.frames[t], resend

    def _take_lost(self, now: float) -> tuple[int, bytes, bool] | None:
        """RLP/2: the lowest frame found lost, unless acknowledged or held meanwhile."""
        while self.resend:
            t = min(self.resend)
            self.resend.discard(t)
            if t > self.last_ack and t not in self.sacked and t in self.frames:
                self.retx.add(t)
                self._stamp(t, now)
                return t, self.frames[t], True
        return None

    def _stamp(self, t: int, now: float) -> None:
        self.sent_at[t] = now
        self._serial += 1
        self.first_tx.setdefault(t, self._serial)
        self.last_tx[t] = self._serial

    def on_wire(self, t: int, now: float) -> None:
        """Ticket `t` is on the line now: its round trip starts here."""
        if t in self.frames:
            self.sent_at[t] = now

    def retransmit_due(self, now: float) -> bool:
        """The oldest unacknowledged frame timed out: go back to it (True) and back off the timeout.
        RLP/2: every frame neither acknowledged nor held that timed out is sent again, alone."""
        if self.selective:
            due = [t for t in range(self.last_ack + 1, self.send_next)
                   if t not in self.sacked and t not in self.resend and t in self.frames
                   and now - self.sent_at.get(t, now) > self.rtt.rto]
            if not due:
                return False
            self.resend.update(due)
            self.rtt.back_off()
            return True
        oldest = self.last_ack + 1
        sent = self.sent_at.get(oldest)
        if sent is not None and oldest < self.send_next and now - sent > self.rtt.rto:
            self.send_next = oldest
            self.rtt.back_off()
            return True
        return False

    def forget_frames(self) -> None:
        """Drop every frame not yet acknowledged (before !ABORT or !RESET)."""
        self.frames.clear()
        self.sent_at.clear()
        self._forget_selective()

    def _forget_selective(self) -> None:
        self.sacked.clear()
        self.resend.clear()
        self.first_tx.clear()
        self.last_tx.clear()

    # -- replies ------------------------------------------------------------------------------
    def acked(self, a: int, now: float) -> None:
        """Everything up to ticket `a` is received by the robot."""
        if a <= self.last_ack or a >= self.next_ticket:
            return
        sent = self.sent_at.get(a)
        # Karn: a frame sent once; RLP/2: not one the robot held behind a gap (its ACK waited)
        if sent is not None and a not in self.retx and a not in self.sacked:
            self.rtt.sample(now - sent)
        for t in range(self.last_ack + 1, a + 1):
            self.frames.pop(t, None)
            self.sent_at.pop(t, None)
            self.retx.discard(t)
            self.sacked.discard(t)
            self.resend.discard(t)
            self.first_tx.pop(t, None)
            self.last_tx.pop(t, None)
        self.last_ack = a
        if self.send_next <= a:
            self.send_next = a + 1

    def executed(self, e: int) -> range:
        """The robot executed up to ticket `e`: the tickets newly executed (empty if none)."""
        if e <= self.last_exec or e >= self.next_ticket:
            return range(0)
        first = self.last_exec + 1
        self.last_exec = e
        self.window_end = max(self.window_end, e + self.capacity)
        return range(first, e + 1)

    def retract(self, e: int) -> bool:
        """An EXE going backwards to ticket `e`: the robot claimed tickets past it that it had not
        executed (a lie about a frame still on the line). The lower claim stands (True when taken
        back): a robot executes in order, and a move counted but never executed would be skipped
        by a resume, while one executed twice is a visible overlap."""
        if e >= self.last_exec:
            return False
        self.last_exec = e
        return True

    def on_ack(self, r: Ack | Sack, now: float) -> bool:
        """A cumulative ACK (RLP/2: with the ranges the robot holds beyond it); True when frames
        were found lost (the sender has resends to make)."""
        a = rlp.unwrap(r.seq, self.last_ack)
        self.acked(a, now)
        if a >= self.last_ack:
            self.window_end = max(self.window_end, a + r.credits)
        if not self.selective:
            return False
        # each ACK / SACK is the robot's whole account: what it no longer lists it does not hold
        held = self._held(a, r.mask, now) if isinstance(r, Sack) else set()
        self.sacked = held
        return self._mark_lost()

    def _held(self, a: int, mask: int, now: float) -> set[int]:
        held = {a + 2 + i for i in range(mask.bit_length()) if mask >> i & 1 and a + 2 + i < self.next_ticket}
        new = [t for t in held - self.sacked if t not in self.retx and t in self.sent_at]
        if new:  # a round trip from the newest frame sent once (Karn)
            t = max(new)
            self.rtt.sample(now - self.sent_at[t])
        return held

    def _mark_lost(self) -> bool:
        """A gap below a held frame whose every copy left before that frame's first copy is lost:
        the line delivers bytes in order. True when any was found."""
        if not self.sacked:
            return False
        evidence, found = -1, False
        for t in range(max(self.sacked), self.last_ack, -1):
            if t in self.sacked:
                evidence = max(evidence, self.first_tx.get(t, -1))
            elif t not in self.resend and self.last_tx.get(t, evidence) < evidence:
                self.resend.add(t)
                found = True
        return found

    def on_nak(self, seq: int, reason: str, now: float) -> bool:
        """True when the sender must go back to the NAKed frame at once."""
        x = rlp.unwrap(seq, self.last_ack + 1)
        self.acked(x - 1, now)  # the robot expects x: it has everything before
        if reason == "FULL":
            self.window_end = min(self.window_end, x - 1)
        sent = self.sent_at.get(x)
        # a NAK sooner than a round trip after x's last transmission is about an earlier one
        min_rtt = self.rtt.min_rtt
        fresh = sent is None or min_rtt is None or now - sent >= 0.7 * min_rtt
        if self.selective:  # RLP/2: x is the lowest gap; send it (alone) again
            if x == self.last_ack + 1 and x < self.send_next and fresh and x not in self.sacked and x not in self.resend:
                self.resend.add(x)
                return True
            return False
        if x == self.last_ack + 1 and x < self.send_next and fresh:
            self.send_next = x
            return True
        return False

    def on_sta(self, r: Sta, now: float) -> range:
        """A STA while streaming: an implicit ACK and EXE; the tickets newly executed."""
        rx_t = rlp.unwrap(r.last_rx, self.last_ack)
        self.acked(rx_t, now)
        self.window_end = max(self.window_end, rx_t + r.queue_free)
        d = rlp.seq_diff(r.last_rx, r.last_exec)
        return self.executed(rx_t - d) if d >= 0 else range(0)

    def implausible(self, r: Reply, *, frames_lost: bool, paused: bool) -> str | None:
        """Why an ACK / EXE cannot have been caused by this host (a protocol fault), else None.

        `frames_lost`: a bad frame arrived since the last ACK (the next EXE may be an implicit
        ACK); `paused`: transmission paused (resynchronising), when replies may lag behind.
        """
        if isinstance(r, (Ack, Sack)):
            a = rlp.unwrap(r.seq, self.last_ack)
            if a > self.max_sent:
                return f"ACK {r.seq:04X} for ticket {a}, never sent (last sent {self.max_sent})"
            if isinstance(r, Sack) and a + 1 + r.mask.bit_length() > self.max_sent:
                return (f"SACK {r.seq:04X} holds ticket {a + 1 + r.mask.bit_length()}, never sent "
                        f"(last sent {self.max_sent})")
        elif isinstance(r, Exe):
            e = rlp.unwrap(r.seq, self.last_exec)
            if e > self.max_sent:
                return f"EXE {r.seq:04X} for ticket {e}, never sent (last sent {self.max_sent})"
            if e < self.last_exec and not paused:
                return f"EXE {r.seq:04X} out of order (ticket {e} after {self.last_exec})"
            if e > self.last_ack and not frames_lost and not paused:
                return f"EXE {r.seq:04X} (ticket {e}) beyond the last ACK ({self.last_ack})"
        return None

    # -- the robot's status -----------------------------------------------------------------------
    def status(self, st: Sta) -> RobotStatus:
        """A STA as a RobotStatus with its sequence numbers unwrapped to tickets."""
        rx_t = rlp.unwrap(st.last_rx, self.last_ack)
        d = rlp.seq_diff(st.last_rx, st.last_exec)
        exec_t = rx_t - d if d >= 0 else rx_t
        return RobotStatus(st.state, st.last_rx, st.last_exec, st.queue_free, st.pos, rx_t, exec_t)

    def resync(self, st: Sta, resume_ticket: int | None) -> str | None:
        """Take the robot's sequence numbers after a (re)connect; a fault text when it lost moves."""
        if resume_ticket is not None:
            rx_t = rlp.unwrap(st.last_rx, resume_ticket)
        elif self.history:
            rx_t = rlp.unwrap(st.last_rx, self.last_ack)
        else:
            rx_t = st.last_rx
        d = rlp.seq_diff(st.last_rx, st.last_exec)
        exec_t = rx_t - d if d >= 0 else rx_t
        self.capacity = st.queue_free + (rx_t - exec_t)
        fault = None
        if self.history and rx_t < self.last_ack:  # the robot forgot moves it had acknowledged (restarted)
            self.forget_frames()
            self.next_ticket = rx_t + 1
            self.aborted_below = self.next_ticket
            fault = (f"robot reports last_rx {st.last_rx:04X} below acknowledged ticket {self.last_ack}: "
                     "it lost queued moves (restarted?); re-plan from last_exec")
        for t in [t for t in self.frames if t <= rx_t]:  # the robot has these: acknowledged
            self.frames.pop(t)
            self.sent_at.pop(t, None)
        self.retx.clear()
        self._forget_selective()
        self.last_ack = rx_t
        self.last_exec = exec_t
        self.next_ticket = max(self.next_ticket if self.history else 0, rx_t + 1)
        self.send_next = rx_t + 1
        self.max_sent = max(rx_t, self.send_next - 1)
        self.window_end = rx_t + st.queue_free
        self.history = True
        return fault

    def after_abort(self, st: Sta) -> RobotStatus:
        """The robot flushed its queue (!ABORT answered by `st`): every move not executed is dropped."""
        rx_t = rlp.unwrap(st.last_rx, self.last_ack)
        if st.state == "IDLE" and not self.capacity:  # standing still: its free-slot count is the whole queue
            # learned only when unknown: the queue size from the connect is what the readiness
            # check holds a flushed queue against (a flush that leaves entries must not shrink it)
            self.capacity = st.queue_free
        self.last_ack = self.max_sent = rx_t
        self.next_ticket = self.send_next = rx_t + 1
        self.last_exec = rx_t - rlp.seq_diff(st.last_rx, st.last_exec)
        self.window_end = rx_t + st.queue_free
        self.aborted_below = self.next_ticket
        return self.status(st)

    def after_reset(self, st: Sta) -> RobotStatus:
        """The robot cleared its queue and counters (!RESET): the next ticket maps to seq 0001."""
        self.capacity = st.queue_free
        base = (self.next_ticket - 1) | 0xFFFF  # the next ticket whose low 16 bits are 0000
        self.last_ack = self.last_exec = self.max_sent = base + 1
        self.next_ticket = self.send_next = base + 2
        self.window_end = base + 1 + st.queue_free
        self.aborted_below = self.next_ticket
        return RobotStatus(st.state, 0, 0, st.queue_free, st.pos, base + 1, base + 1)

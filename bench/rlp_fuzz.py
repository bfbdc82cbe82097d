"""Robot link fuzz: the host's window (drivers/rlp_window.py, with the reply handling of
drivers/robot.py) against the robot simulator's receiver (sims/robot_sim.py, fed its bytes through
`attach`/`feed`) over a virtual serial line that corrupts and drops bytes at random, in virtual
time: no sockets, no sleeping, so 10^6 frames take minutes and every run is reproducible from its
seed. The judge is the simulator's own record of what it executed: every move exactly once, in
order (nothing lost, duplicated or reordered).

    .venv/bin/python -m bench.rlp_fuzz                      # 10^6 frames at 1e-2 byte errors, RLP/2
    .venv/bin/python -m bench.rlp_fuzz --frames 200000 --corrupt 0.001 --drop 0.0001 --protocol 1

The line: 8N1 at `baud` (bytes serialised at baud/10 per second), `latency_s` one way; each byte is
hit with probability `corrupt` (one random bit flipped) or `drop` (lost), independently, in both
directions. The host sends a keepalive `!STATUS` after 0.5 s without traffic and checks its
retransmission timeout every 20 ms, as RobotLink does.
"""
from __future__ import annotations

import argparse
import heapq
import json
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np

from drivers.rlp_window import RtoEstimator, TicketWindow
from drivers.robot import RobotLink
from drivers.robot_records import Ack, Exe, Nak, Sack, Sta, decode_reply
from sims.clock import SimClock
from sims.robot_sim import RobotSim
from wire import rlp

SPEED = 1500.0
TICK_S = RobotLink.TICK_S


@dataclass
class FuzzResult:
    protocol: int
    moves: int
    frames_sent: int
    resends: int
    timeouts: int
    executed: int
    lost: int               # planned moves the robot never executed
    duplicated: int         # moves it executed more than once
    reordered: int          # executed moves out of plan order
    exactly_once_in_order: bool
    robot_duplicates: int   # frames the robot received again (acknowledged, not queued)
    robot_bad_frames: int
    virtual_s: float
    wall_s: float
    fraction_of_line: float  # bytes of unique move frames per second of virtual time / line rate


class Line:
    """One direction of the serial line: serialised at `rate` bytes/s, then `latency` s."""

    def __init__(self, rng: np.random.Generator, rate: float, latency: float, corrupt: float, drop: float) -> None:
        self.rng, self.rate, self.latency = rng, rate, latency
        self.corrupt, self.drop = corrupt, drop
        self.free_at = 0.0
        p = corrupt + drop
        self.gap = int(rng.geometric(p)) - 1 if p > 0 else 0   # clean bytes before the next hit

    def send(self, now: float, data: bytes) -> tuple[float, bytes]:
        """(arrival time of the last byte, the bytes as they arrive)."""
        start = max(now, self.free_at)
        self.free_at = start + len(data) / self.rate
        return self.free_at + self.latency, self.mangle(data)

    def mangle(self, data: bytes) -> bytes:
        """Each byte independently: corrupted (one random bit flipped) or dropped. The clean bytes
        between two hits are drawn at once (geometric), so a clean frame costs no random draw."""
        p = self.corrupt + self.drop
        if p <= 0:
            return data
        n, pos = len(data), 0
        if self.gap >= n:
            self.gap -= n
            return data
        out = bytearray()
        while self.gap < n - pos:
            i = pos + self.gap
            out += data[pos:i]
            if self.rng.random() * p < self.corrupt:
                out.append(data[i] ^ (1 << int(self.rng.integers(0, 8))))
            pos = i + 1
            self.gap = int(self.rng.geometric(p)) - 1
        self.gap -= n - pos
        out += data[pos:]
        return bytes(out)


class Host:
    """The RobotLink reply handling over a bare TicketWindow (drivers/robot.py `_dispatch`)."""

    def __init__(self, protocol: int, slots: int) -> None:
        lo, hi = RobotLink.RTO_BOUNDS[protocol]
        self.w = TicketWindow(RtoEstimator(lo, hi, deque(maxlen=64)))
        self.w.resync(Sta("IDLE", 0, 0, slots, (0.0, 0.0, 0.0)), None)
        self.w.selective = protocol >= 2
        self.splitter = rlp.LineSplitter()
        self.resends = self.timeouts = self.frames_sent = 0
        self.faults: list[str] = []

    def receive(self, data: bytes, now: float) -> None:
        for line in self.splitter.feed(data):
            try:
                r = decode_reply(line)
            except rlp.FrameError:
                continue
            fault = self.w.implausible(r, frames_lost=True, paused=False)
            if fault is not None:
                self.faults.append(fault)
                continue
            if isinstance(r, (Ack, Sack)):
                self.w.on_ack(r, now)
            elif isinstance(r, Nak):
                self.w.on_nak(r.seq, r.reason, now)
            elif isinstance(r, Exe):
                self.w.executed(rlp.unwrap(r.seq, self.w.last_exec))
            elif isinstance(r, Sta):
                self.w.on_sta(r, now)


def _move(i: int) -> tuple[str, float, float, float, float, float, float, float]:
    return ("MOVL", float(i % 100), float((i // 100) % 100), 5.0, 0.0, 0.0, 1.0, SPEED)


class Bench:
    """The host, the line and the robot simulator, stepped from event to event in virtual time."""

    def __init__(self, *, seed: int, corrupt: float, drop: float, protocol: int, slots: int, baud: int,
                 latency_s: float, time_scale: float) -> None:
        rng = np.random.default_rng(seed)
        self.up, self.down = (Line(rng, baud / 10.0, latency_s, corrupt, drop) for _ in range(2))
        self.sim = RobotSim(clock=SimClock(time_scale), queue_slots=slots, record=True)
        self.time_scale = time_scale
        self.events: list[tuple[float, int, str, bytes]] = []
        self.n_ev = 0
        self.now = self.last_tx = self.t_exec = self.next_tick = 0.0
        self.sim.attach(self._robot_writes)
        if protocol >= 2:  # negotiated over a clean line first (bench/link.py measures the real one)
            self.sim.feed(rlp.encode("!PROTO 2"))
        self.host = Host(protocol, slots)
        self.host.receive(b"".join(data for _, _, _, data in self.events), 0.0)
        self.events.clear()

    def _push(self, t: float, to: str, data: bytes) -> None:
        self.n_ev += 1
        heapq.heappush(self.events, (t, self.n_ev, to, data))

    def _robot_writes(self, data: bytes) -> None:
        t, got = self.down.send(self.now, data)
        self._push(t, "host", got)

    def send(self) -> None:
        """The host transmits its next frame when its line is free."""
        if self.up.free_at > self.now:
            return
        nxt = self.host.w.take_next(None, self.now)
        if nxt is None:
            return
        t_id, data, resend = nxt
        self.host.resends += resend
        self.host.frames_sent += 1
        t, got = self.up.send(self.now, data)
        self.host.w.on_wire(t_id, self.now)
        self.last_tx = self.now
        self._push(t, "robot", got)

    def step(self) -> None:
        """On to the next thing that happens: a delivery, the line free again, the host's timer tick."""
        t_next = min(self.events[0][0] if self.events else float("inf"), self.next_tick)
        if self.up.free_at > self.now:
            t_next = min(t_next, self.up.free_at)
        self.now = max(self.now, t_next)
        while self.events and self.events[0][0] <= self.now:
            _, _, to, data = heapq.heappop(self.events)
            if to == "robot":
                self.sim.feed(data)
            else:
                self.host.receive(data, self.now)
        self.t_exec = self.sim.advance(self.t_exec, self.now * self.time_scale)
        self.sim.flush_exe()
        if self.now >= self.next_tick:
            self.tick()

    def tick(self) -> None:
        """The host's timer: retransmission timeout and keepalive."""
        self.next_tick = self.now + TICK_S
        if self.host.w.retransmit_due(self.now):
            self.host.timeouts += 1
        if self.now - self.last_tx > 0.5:
            self.last_tx = self.now
            t, got = self.up.send(self.now, rlp.encode("!STATUS"))
            self._push(t, "robot", got)


def run(moves: int, *, seed: int = 1, corrupt: float = 0.01, drop: float = 0.001, protocol: int = 2,
        slots: int = 64, baud: int = 115200, latency_s: float = 0.002, time_scale: float = 1000.0,
        max_frames: int | None = None) -> FuzzResult:
    """Stream `moves` 1 mm moves (or until `max_frames` frames were sent) and judge the robot's record."""
    b = Bench(seed=seed, corrupt=corrupt, drop=drop, protocol=protocol, slots=slots, baud=baud,
              latency_s=latency_s, time_scale=time_scale)
    w, host = b.host.w, b.host
    more = max_frames if max_frames is not None else float("inf")
    queued = unique_bytes = 0
    wall0 = time.monotonic()
    while w.last_exec < min(moves, queued if host.frames_sent >= more else moves):
        while queued < moves and w.has_room() and host.frames_sent < more:
            frame = rlp.encode_move(w.next_ticket, *_move(queued))
            unique_bytes += len(frame)
            w.queue(frame)
            queued += 1
        b.send()
        b.step()
        if b.now > 1e7:
            raise RuntimeError("the link stopped making progress")
    done = b.sim.executed or []
    lost, dup, reordered = judge(done, queued)
    planned = [(i + 1) & 0xFFFF for i in range(queued)]
    return FuzzResult(protocol=protocol, moves=queued, frames_sent=host.frames_sent, resends=host.resends,
                      timeouts=host.timeouts, executed=len(done), lost=lost, duplicated=dup, reordered=reordered,
                      exactly_once_in_order=done == planned and not host.faults, robot_duplicates=b.sim.duplicates,
                      robot_bad_frames=b.sim.crc_errors + b.sim.syntax_errors, virtual_s=round(b.now, 3),
                      wall_s=round(time.monotonic() - wall0, 1),
                      fraction_of_line=round(unique_bytes / max(b.now, 1e-9) / (baud / 10.0), 4))


def judge(done: list[int], planned: int) -> tuple[int, int, int]:
    """(lost, duplicated, reordered) of the robot's executed wire seqs against tickets 1..planned:
    each seq is unwrapped next to the one executed before it (the 16-bit numbers wrap)."""
    tickets, ref = [], 0
    for seq in done:
        ref = rlp.unwrap(seq, ref)
        tickets.append(ref)
    uniq = set(tickets)
    lost = len(set(range(1, planned + 1)) - uniq)
    reordered = sum(1 for a, b in zip(tickets, tickets[1:]) if b < a)
    return lost, len(tickets) - len(uniq), reordered


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.rlp_fuzz", description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000, help="frames to send (moves follow from the losses)")
    ap.add_argument("--corrupt", type=float, default=0.01)
    ap.add_argument("--drop", type=float, default=0.001)
    ap.add_argument("--protocol", type=int, default=2, choices=(1, 2))
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    res = run(10 ** 9, seed=args.seed, corrupt=args.corrupt, drop=args.drop, protocol=args.protocol,
              max_frames=args.frames)
    print(json.dumps(asdict(res), indent=1))
    return 0 if res.exactly_once_in_order else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

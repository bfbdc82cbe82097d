"""The records of the robot link (RLP/1): what it reports to the controller, its statistics, and
the robot's replies as one typed record per kind.

`wire.rlp.parse_reply` returns one `Reply` with every field optional (the codec is shared with
the simulator); `typed_reply` turns it into the record of its kind with the fields that kind
always has, so the driver never handles a `None` sequence number.
"""
from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import AsyncIterator, Callable, TypeVar

from drivers.liveness import LinkHealth
from wire import rlp

Pos = tuple[float, float, float]
V = TypeVar("V")


@dataclass(frozen=True)
class RobotStatus:
    """The robot's answer to a control frame (STA), with the sequence numbers as tickets too."""

    state: str
    last_rx: int
    last_exec: int
    queue_free: int
    pos: Pos
    last_rx_ticket: int = 0
    last_exec_ticket: int = 0


@dataclass(frozen=True)
class RobotEvent:
    """kind: EXE (ticket), MRK (value n), ERR (value code, text), HB (value n), STA (value: the Sta),
    link_lost (text), link_restored (value: the RobotStatus)."""

    kind: str
    ticket: int | None = None
    value: object = None
    text: str = ""
    t: float = 0.0


class EventHub:
    """The link's listeners: callbacks and async iterators, each given every event in order."""

    def __init__(self) -> None:
        self._callbacks: list[Callable[[RobotEvent], None]] = []
        self._queues: list[asyncio.Queue[RobotEvent]] = []

    @property
    def listening(self) -> bool:
        return bool(self._callbacks or self._queues)

    def add(self, fn: Callable[[RobotEvent], None]) -> None:
        self._callbacks.append(fn)

    async def stream(self) -> AsyncIterator[RobotEvent]:
        """Every event from now on (an async iterator)."""
        q: asyncio.Queue[RobotEvent] = asyncio.Queue()
        self._queues.append(q)
        try:
            while True:
                yield await q.get()
        finally:
            self._queues.remove(q)

    def emit(self, ev: RobotEvent) -> None:
        for fn in self._callbacks:
            fn(ev)
        for q in self._queues:
            q.put_nowait(ev)


@dataclass
class LinkStats(LinkHealth):
    """LinkHealth (heard, late, bad, lost, round trips) and the RLP/1 counters."""

    frames_sent: int = 0
    frames_received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    resends: int = 0
    timeouts: int = 0
    crc_errors: int = 0      # robot frames received with a bad CRC
    bad_frames: int = 0      # robot frames with a bad syntax
    naks: int = 0            # NAKs received from the robot
    naks_by_reason: dict[str, int] = field(default_factory=dict)
    sacks: int = 0           # RLP/2 SACK frames received (the robot held frames beyond a gap)
    protocol: int = 1        # the RLP version negotiated at the last connect
    reconnects: int = 0
    heartbeats: int = 0      # HB-looking lines received (a flood counts every one)
    hb_skipped: int = 0      # of those, not decoded (over the per-read bound)
    protocol_faults: int = 0

    def as_dict(self) -> dict[str, float | int | dict[str, int]]:
        return {"frames_sent": self.frames_sent, "frames_received": self.frames_received,
                "bytes_sent": self.bytes_sent, "bytes_received": self.bytes_received,
                "resends": self.resends, "timeouts": self.timeouts, "crc_errors": self.crc_errors,
                "bad_frames": self.bad_frames, "naks": self.naks, "naks_by_reason": dict(self.naks_by_reason),
                "sacks": self.sacks, "protocol": self.protocol,
                "reconnects": self.reconnects, "heartbeats": self.heartbeats, "hb_skipped": self.hb_skipped,
                "protocol_faults": self.protocol_faults, **super().as_dict()}


# -- the robot's replies, one record per kind -------------------------------------------------------


@dataclass(frozen=True)
class Ack:
    seq: int
    credits: int


@dataclass(frozen=True)
class Sack:
    """RLP/2: a cumulative ACK of `seq`; bit i of `mask` set = frame seq + 2 + i is held."""

    seq: int
    credits: int
    mask: int


@dataclass(frozen=True)
class Proto:
    """RLP/2 negotiation: the protocol version the robot now speaks on this link."""

    version: int


@dataclass(frozen=True)
class Nak:
    seq: int
    reason: str


@dataclass(frozen=True)
class Exe:
    seq: int


@dataclass(frozen=True)
class Sta:
    state: str
    last_rx: int
    last_exec: int
    queue_free: int
    pos: Pos


@dataclass(frozen=True)
class Mrk:
    n: int


@dataclass(frozen=True)
class Hb:
    n: int


@dataclass(frozen=True)
class Err:
    code: int
    text: str


Reply = Ack | Sack | Proto | Nak | Exe | Sta | Mrk | Hb | Err


def _need(v: V | None, kind: str, name: str) -> V:
    if v is None:
        raise rlp.FrameError("SYNTAX", f"{kind} without its {name}")
    return v


def typed_reply(r: rlp.Reply) -> Reply:
    """The record of `r`'s kind; FrameError(SYNTAX) for a reply missing a field of its kind."""
    k = r.kind
    if k == "ACK":
        return Ack(_need(r.seq, k, "seq"), _need(r.credits, k, "credits"))
    if k == "SACK":
        return Sack(_need(r.seq, k, "seq"), _need(r.credits, k, "credits"), _need(r.mask, k, "mask"))
    if k == "PROTO":
        return Proto(_need(r.n, k, "version"))
    if k == "NAK":
        return Nak(_need(r.seq, k, "seq"), _need(r.reason, k, "reason"))
    if k == "EXE":
        return Exe(_need(r.seq, k, "seq"))
    if k == "STA":
        return Sta(_need(r.state, k, "state"), _need(r.last_rx, k, "last_rx"), _need(r.last_exec, k, "last_exec"),
                   _need(r.queue_free, k, "queue_free"), _need(r.pos, k, "pos"))
    if k == "MRK":
        return Mrk(_need(r.n, k, "n"))
    if k == "HB":
        return Hb(_need(r.n, k, "n"))
    if k == "ERR":
        return Err(_need(r.code, k, "code"), r.text or "")
    raise rlp.FrameError("SYNTAX", f"unknown robot frame kind {k!r}")


def decode_reply(line: bytes) -> Reply:
    """One received line as a typed reply; FrameError (reason CRC or SYNTAX) if it is not one."""
    return typed_reply(rlp.parse_reply(rlp.decode(line)))

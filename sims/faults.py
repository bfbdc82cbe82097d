"""Seeded fault injection: the fault-spec parser, the fault channel and the baud throttle.

A fault spec is a comma-separated list of `key=value` and `event@cond=value` entries, e.g.
`seed=7,corrupt=0.01,drop=0.001,burst=32,latency=2ms,stall=5s,unplug@t=12s,arc_loss@layer=3`.
KEYS below is the one table of known keys; each value is parsed with its unit (durations take
`ms` or `s`, a bare number is seconds). Device simulators read their own keys with
`FaultSpec.value(name, default)` and `FaultSpec.events(name)`; `FaultSpec.rng(stream)` gives a
seeded numpy Generator per named stream so every run with the same seed is the same.

The channel (`FaultPipe`, one per direction) sits between a simulator and its transport and
applies, per byte: drop, bit-flip corruption (in bursts of `burst` bytes), fixed latency,
stalls (nothing moves, bytes are held) and a throughput limit of baud/10 bytes/s (8N1: 10 bits
per byte, so 115200 baud carries at most 11,520 bytes/s). `unplug` events are acted on by the
transport (sims/transport.py): it closes the connection.
"""
from __future__ import annotations

import asyncio
import re
import time
import zlib
from dataclasses import dataclass, field
from typing import Callable, overload

import numpy as np

from core.errors import ConfigError

# key -> (kind, description). Kinds: int, prob (0..1), dur (ms / s), count (int >= 1),
# event (only as `key@cond=value`). Every key may also appear as an event.
KEYS: dict[str, tuple[str, str]] = {
    # link faults (robot and CNC serial links)
    "seed": ("int", "seed of every random stream"),
    "corrupt": ("prob", "fraction of bytes whose bits are flipped"),
    "burst": ("count", "corrupted bytes come in bursts of this length (default 1)"),
    "drop": ("prob", "probability that a byte is dropped"),
    "latency": ("dur", "one-way delay added to every byte"),
    "stall": ("dur", "length of each stall (bytes held, nothing moves); when: stall@t=..."),
    "unplug": ("dur", "how long the cable stays out (default 0: replug at once); when: unplug@t=..."),
    "baud": ("int", "throttle the simulated serial link to baud/10 bytes/s"),
    # misbehaving robot (sims/robot_sim.py; issue 13): when given as `name@t=...` (wall seconds
    # since the simulator started) or `name@move=N` (after N executed moves); a bare `name=0`
    # starts at once
    "flood": ("dur", "send valid HB frames as fast as the line carries them; when: flood@t=... / @move=N"),
    "lie": ("dur", "ACK and EXE a sequence number never sent; when: lie@t=... / @move=N"),
    "garble": ("dur", "every reply with a bad CRC from then on; when: garble@t=... / @move=N"),
    "mute": ("dur", "no reply at all from then on; when: mute@t=... / @move=N"),
    # a motion device that stops executing (issue 26; robot: RUN, no EXE; CNC: Run, MPos still).
    # @travel=N: at the N-th travel move (robot MOVJ, CNC G0); CNC only: @probe=N at the N-th
    # probing move (G38.x, it never ends), @home=N in the N-th homing cycle (it never finishes)
    "freeze": ("dur", "accept moves but stop executing them from then on; when: freeze@t=... / @move=N / "
                      "@travel=N / @probe=N (CNC) / @home=N (CNC)"),
    # a robot whose flush leaves phantom entries: from the first !ABORT on, this many queue slots
    # stay taken while it reports IDLE (the readiness check must see the queue is not empty)
    "phantom": ("int", "robot: queue slots still taken after !ABORT while it reports IDLE"),
    # a power source whose error stays latched across restarts (kept in its log/state dir)
    "latched_error": ("int", "power source starts with this error number latched (e.g. 50, watchdog)"),
    # device faults (power source, cell I/O), read by their simulators
    "ignition_fail": ("prob", "probability that an arc ignition attempt fails"),
    "arc_loss": ("dur", "length of an arc loss; when: arc_loss@layer=N or @t=..."),
    "wire_stick": ("dur", "wire stick at arc end; when: wire_stick@t=... / @layer=N"),
    "gas_fault": ("dur", "gas fault duration; when: gas_fault@t=..."),
    "wire_out": ("dur", "wire-out duration; when: wire_out@t=..."),
    "silence": ("dur", "the device stops answering for this long; when: silence@t=..."),
    "door_open": ("dur", "door opened for this long; when: door_open@t=..."),
    "estop": ("dur", "E-stop pressed for this long; when: estop@t=..."),
}
# event condition -> kind of its value
CONDITIONS: dict[str, str] = {"t": "dur", "layer": "int", "pass": "int", "move": "int", "frame": "int",
                              "travel": "int", "probe": "int", "home": "int"}

_DUR_RE = re.compile(r"^(\d+(?:\.\d*)?|\.\d+)(ms|s)?$")


def parse_duration(text: str, key: str) -> float:
    """'2ms' -> 0.002, '5s' / '5' -> 5.0; ConfigError naming the key otherwise."""
    m = _DUR_RE.match(text.strip())
    if m is None:
        raise ConfigError(f"fault spec: key '{key}': bad duration {text!r} (use e.g. 2ms or 5s)")
    v = float(m.group(1))
    return v / 1000.0 if m.group(2) == "ms" else v


def _parse_value(kind: str, text: str, key: str) -> float | int:
    text = text.strip()
    if kind == "dur":
        return parse_duration(text, key)
    try:
        if kind in ("int", "count"):
            v = int(text)
            if kind == "count" and v < 1:
                raise ValueError
            if v < 0:
                raise ValueError
            return v
        if kind == "prob":
            p = float(text)
            if not 0.0 <= p <= 1.0:
                raise ValueError
            return p
    except ValueError:
        pass
    expect = {"int": "a non-negative integer", "count": "an integer >= 1", "prob": "a probability in [0, 1]"}[kind]
    raise ConfigError(f"fault spec: key '{key}': bad value {text!r}, expected {expect}")


@dataclass(frozen=True)
class FaultSpec:
    """A parsed fault spec: plain values and (condition, value) events, plus seeded RNG streams."""

    values: dict[str, float | int] = field(default_factory=dict)
    event_list: tuple[tuple[str, str, float | int], ...] = ()
    text: str = ""

    @property
    def seed(self) -> int:
        return int(self.values.get("seed", 0))

    @overload
    def value(self, name: str) -> float | int | None: ...
    @overload
    def value(self, name: str, default: float) -> float | int: ...
    @overload
    def value(self, name: str, default: None) -> float | int | None: ...

    def value(self, name: str, default: float | int | None = None) -> float | int | None:
        """The plain value of `name` (e.g. corrupt=0.01), or `default` when not given."""
        if name not in KEYS:
            raise KeyError(f"unknown fault key {name!r}")
        return self.values.get(name, default)

    def events(self, name: str) -> list[tuple[str, float | int]]:
        """The `name@cond=value` entries as (cond, value), in spec order (t in seconds)."""
        if name not in KEYS:
            raise KeyError(f"unknown fault key {name!r}")
        return [(c, v) for n, c, v in self.event_list if n == name]

    def rng(self, stream: str) -> np.random.Generator:
        """A generator seeded by the spec's seed and the stream name: reproducible per stream."""
        return np.random.default_rng([self.seed, zlib.crc32(stream.encode())])

    def __bool__(self) -> bool:
        return bool(self.values) or bool(self.event_list)


def parse_fault_spec(spec: str | None) -> FaultSpec:
    """Parse `key=value,event@cond=value,...`; an unknown key or bad value is a ConfigError."""
    values: dict[str, float | int] = {}
    events: list[tuple[str, str, float | int]] = []
    for raw in (spec or "").split(","):
        item = raw.strip()
        if not item:
            continue
        if "=" not in item:
            raise ConfigError(f"fault spec: entry {item!r} needs a value (key=value or event@cond=value)")
        left, val = item.split("=", 1)
        left = left.strip()
        if "@" in left:
            name, cond = (s.strip() for s in left.split("@", 1))
            if name not in KEYS:
                raise ConfigError(f"fault spec: unknown key '{name}'; known keys: {', '.join(KEYS)}")
            if cond not in CONDITIONS:
                raise ConfigError(f"fault spec: key '{name}': unknown condition '{cond}'; use one of {', '.join(CONDITIONS)}")
            events.append((name, cond, _parse_value(CONDITIONS[cond], val, f"{name}@{cond}")))
        else:
            if left not in KEYS:
                raise ConfigError(f"fault spec: unknown key '{left}'; known keys: {', '.join(KEYS)}")
            kind = KEYS[left][0]
            values[left] = _parse_value(kind, val, left)
    return FaultSpec(values, tuple(events), spec or "")


def bytes_per_second(baud: int) -> float:
    """Payload rate of an 8N1 serial line: 10 bits on the wire per byte."""
    return baud / 10.0


class FaultPipe:
    """One direction of a simulated serial line: faults, latency, stalls and the baud throttle.

    `send(data)` queues bytes; a task hands them to `deliver` in order, never faster than
    `rate` bytes/s (None: unthrottled). `t0` is the monotonic time of `t` in stall events.
    Counters: bytes_in, bytes_out, dropped, corrupted.
    """

    CHUNK_S = 0.002      # the throttle's tick
    MAX_BURST_S = 0.02   # line time a late tick may catch up on (never banked while idle)

    def __init__(self, deliver: Callable[[bytes], None], spec: FaultSpec | None = None, *,
                 stream: str = "link", rate: float | None = None, t0: float | None = None) -> None:
        self._deliver = deliver
        spec = spec or FaultSpec()
        self.spec = spec
        self._rng = spec.rng(stream)
        self.corrupt = float(spec.value("corrupt", 0.0))
        self.burst = int(spec.value("burst", 1))
        self.drop = float(spec.value("drop", 0.0))
        self.latency = float(spec.value("latency", 0.0))
        self.rate = rate
        self.t0 = time.monotonic() if t0 is None else t0
        stall = float(spec.value("stall", 0.0))
        self.stalls = [(float(v), float(v) + stall) for c, v in spec.events("stall") if c == "t" and stall > 0]
        self._buf = bytearray()
        self._burst_left = 0
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = asyncio.get_running_loop().create_task(self._run())
        self.bytes_in = self.bytes_out = self.dropped = self.corrupted = 0
        self.stalled_until = 0.0

    def send(self, data: bytes) -> None:
        self.bytes_in += len(data)
        self._buf += data
        self._wake.set()

    def stall(self, seconds: float) -> None:
        """Stall this direction now for `seconds` (bytes are held, then delivered)."""
        self.stalled_until = max(self.stalled_until, time.monotonic() + seconds)

    def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            self._task = None

    def _stalled(self, now: float) -> float:
        """Seconds until the current stall ends (0 when not stalled)."""
        end = self.stalled_until
        t = now - self.t0
        for a, b in self.stalls:
            if a <= t < b:
                end = max(end, self.t0 + b)
        return max(0.0, end - now)

    def _mangle(self, chunk: bytes) -> bytes:
        if not (self.corrupt or self.drop):
            return chunk
        a = np.frombuffer(chunk, dtype=np.uint8).copy()
        n = len(a)
        if self.corrupt:
            # corruption events start with probability corrupt/burst per byte and hit `burst` bytes
            hit = np.zeros(n, dtype=bool)
            k = min(self._burst_left, n)
            hit[:k] = True
            self._burst_left -= k
            starts = np.flatnonzero(self._rng.random(n) < self.corrupt / self.burst)
            for s in starts:
                hit[s:s + self.burst] = True
                self._burst_left = max(self._burst_left, int(s) + self.burst - n)
            idx = np.flatnonzero(hit)
            if len(idx):
                a[idx] ^= (1 << self._rng.integers(0, 8, len(idx))).astype(np.uint8)
                self.corrupted += len(idx)
        if self.drop:
            keep = self._rng.random(n) >= self.drop
            self.dropped += int(n - keep.sum())
            a = a[keep]
        return a.tobytes()

    async def _run(self) -> None:
        # The line is a serializer: a byte is handed over when its last bit would have arrived
        # (`free` is when the line finishes what it already carries). Bytes go in chunks of at
        # most CHUNK_S of line time; a late tick may catch up by at most MAX_BURST_S.
        loop = asyncio.get_running_loop()
        free = time.monotonic()
        while True:
            if not self._buf:
                self._wake.clear()
                await self._wake.wait()
                free = max(free, time.monotonic())  # an idle line banks no time
            now = time.monotonic()
            wait = self._stalled(now)
            if wait > 0:
                await asyncio.sleep(min(wait, 0.05))
                free = time.monotonic()
                continue
            if self.rate is None:
                n = len(self._buf)
            else:
                free = max(free, now - self.MAX_BURST_S)
                n = min(len(self._buf), max(1, int((now + self.CHUNK_S - free) * self.rate)))
                free += n / self.rate
                if free > now:
                    await asyncio.sleep(free - now)
            chunk = bytes(self._buf[:n])
            del self._buf[:n]
            out = self._mangle(chunk)
            self.bytes_out += len(out)
            if out:
                if self.latency > 0:
                    loop.call_later(self.latency, self._deliver, out)
                else:
                    self._deliver(out)

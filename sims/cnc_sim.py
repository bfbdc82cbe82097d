"""CNC simulator: a 5-axis (XYZAB) controller speaking the grbl 1.1 serial interface.

Byte for byte what a grbl 1.1h controller answers (docs/protocols/grbl.md): a 128-byte serial
RX ring (127 usable; bytes that arrive while it is full are lost, as with the real ISR), the
real-time bytes `?` `!` `~` 0x18 picked out before the buffer, an 80-character line buffer, a
15-block planner, `ok` / `error:N` / `ALARM:N`, status reports, `$` system commands, homing and
unlock, probing against a virtual workpiece (sims/workpiece.py) and motion executed in
simulated time (SimClock) at the commanded feed. Every executed G-code line is appended to
`cnc.jsonl` ({"seq", "verb", "target", "t", "line"}), every stretch of motion is reported to the
World. Served on loopback TCP or a pty through sims/transport.py (fault channel, baud throttle).
"""
from __future__ import annotations

import asyncio
import json
import math
import re
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Callable

import numpy as np

from wire.grbl_protocol import GrblStatus, fmt, format_probe, format_status
from sims.clock import SimClock
from sims.faults import parse_fault_spec
from sims.process_world import attach
from sims.transport import serve_serial
from sims.workpiece import Workpiece

DEVICE = "cnc"
VERSION = "1.1h"
BANNER = f"Grbl {VERSION} ['$' for help]"
LINE_BUFFER_SIZE = 80     # grbl: at most 79 characters per line after stripping
PLANNER_BLOCKS = 15       # grbl 1.1 on a 328p: BLOCK_BUFFER_SIZE 16, one kept free

Pos5 = tuple[float, float, float, float, float]

# The `$$` listing: grbl 1.1 defaults, with axis settings for A and B as the 5-axis ports
# (grbl-Mega-5X) number them ($1x3 = A, $1x4 = B). Rates mm/min (deg/min), accel mm/s².
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.000, 25: 500.000, 26: 250, 27: 1.000, 30: 1000, 31: 0, 32: 0,
    100: 250.000, 101: 250.000, 102: 250.000, 103: 100.000, 104: 100.000,
    110: 6000.000, 111: 6000.000, 112: 3000.000, 113: 7200.000, 114: 7200.000,
    120: 250.000, 121: 250.000, 122: 250.000, 123: 250.000, 124: 250.000,
    130: 1000.000, 131: 1000.000, 132: 500.000, 133: 360.000, 134: 360.000,
}
_INT_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}

_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")


@dataclass
class Block:
    """One planner entry, or a non-motion line kept in order for the execution log."""

    seq: int
    verb: str
    line: str
    target: Pos5 | None = None
    feed: float = 0.0                    # mm/min (rapids: the max rate)
    s: float = 0.0                       # laser / process power in effect
    spindle: bool | None = None          # M3/M4 → True, M5 → False, None: no change
    probe: str | None = None             # "G38.2" | "G38.3"
    started: bool = False
    done: bool = False
    contact: bool = False

    @property
    def motion(self) -> bool:
        return self.target is not None


class GrblError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class CncSim:
    """In-process grbl 1.1 controller. Drive it with attach/feed/detach (sims.transport.ByteSim)."""

    def __init__(self, *, clock: SimClock, world: object | None = None, workpiece: Workpiece | None = None,
                 log_path: str | Path | None = None, rx_buffer_bytes: int = 128,
                 planner_blocks: int = PLANNER_BLOCKS, homing_enabled: bool = True,
                 home: Pos5 | None = None, tick_s: float = 0.002, letters: str = "XYZAB") -> None:
        self.clock = clock
        self.letters = letters  # XYZAB or XYZAC: the rotary letters of the configured table
        self.world = world
        self.workpiece = workpiece
        self.tick_s = tick_s
        self.rx_capacity = rx_buffer_bytes - 1  # a ring buffer of N bytes holds N-1
        self.planner_blocks = planner_blocks
        self.settings = dict(DEFAULT_SETTINGS)
        self.settings[22] = 1 if homing_enabled else 0
        self.home = home if home is not None else self._default_home()
        self.pos: list[float] = list(self.home)   # powered up where it was parked
        self.alarm = bool(self.settings[22])      # HOMING_INIT_LOCK: locked until $H / $X
        self.homing = False
        self.homed = False
        self.hold = False
        self.hold_sub = 0
        self.spindle_on = False
        self.spindle_s = 0.0
        self.probe_pos: Pos5 = (0.0,) * 5
        self.probe_ok = False
        # counters for tests and benchmarks
        self.rx_dropped = 0
        self.rx_bytes = 0
        self.lines_received = 0
        self.executed: deque[Block] = deque(maxlen=10_000)   # the most recent executed lines
        self.executed_count = 0
        self.starved = 0          # times the planner ran empty while lines were still arriving
        self._rx = bytearray()
        self.hung = False    # a firmware whose main loop stopped reading its input (tests set it)
        self.freeze: tuple[str, float] | None = None  # fault `freeze@t=`/`@move=`: Run, no motion
        self._t0 = time.monotonic()
        self._line: list[str] = []
        self._overflow = False
        self._comment = 0
        self._queue: deque[Block] = deque()
        self._motion_in_queue = 0
        self._reset_modal()
        self._gc_pos: list[float] = list(self.pos)
        self._latch: tuple[float, ...] | None = None
        self._hold_t: float | None = None
        self._hold_v = 0.0
        self._write: Callable[[bytes], None] | None = None
        self._rx_event = asyncio.Event()
        self._work = asyncio.Event()
        self._changed = asyncio.Event()
        self._proto: asyncio.Task | None = None
        self._exec: asyncio.Task | None = None
        self._log: IO[str] | None = None
        self._log_dirty = False
        if log_path is not None:
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            self._log = open(log_path, "a", encoding="utf-8")

    def _default_home(self) -> Pos5:
        # Parked 50 mm above the workpiece's highest point (rounded up to 10 mm), so the probe
        # is clear of the part after power-up and after homing.
        top = 0.0
        if self.workpiece is not None:
            m = self.workpiece.part_to_machine()
            wp = self.workpiece
            pts = np.concatenate([wp._v0, wp._v0 + wp._e1, wp._v0 + wp._e2])
            v = pts @ m[:3, :3].T + m[:3, 3]
            top = max(float(v[:, 2].max()), 0.0)
        return (0.0, 0.0, 50.0 + math.ceil(top / 10.0) * 10.0, 0.0, 0.0)

    def _reset_modal(self) -> None:
        self.motion_mode = "G0"
        self.absolute = True
        self.inches = False
        self.feed_rate = 0.0
        self.s_word = 0.0
        self.inverse_time = False  # G93

    # -- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._proto = loop.create_task(self._protocol_loop())
        self._exec = loop.create_task(self._exec_loop())

    async def close(self) -> None:
        for t in (self._proto, self._exec):
            if t is not None:
                t.cancel()
        for t in (self._proto, self._exec):
            if t is not None:
                try:
                    await t
                except asyncio.CancelledError:
                    pass
        self._proto = self._exec = None
        if self._log is not None:
            self._log.close()
            self._log = None

    # -- ByteSim ----------------------------------------------------------------------------
    def attach(self, write: Callable[[bytes], None]) -> None:
        # Like a controller on a plain RS-232 line: opening the port does not reset it.
        self._write = write

    def detach(self) -> None:
        self._write = None

    def feed(self, data: bytes) -> None:
        """The serial RX interrupt: real-time bytes act at once, the rest go to the RX ring."""
        for b in data:
            if b == 0x3F:                 # '?'
                self._send(self.status_line())
            elif b == 0x21:               # '!'
                self._feed_hold()
            elif b == 0x7E:               # '~'
                self._cycle_start()
            elif b == 0x18:
                self.soft_reset()
            elif b >= 0x80:
                pass                      # extended real-time (overrides, door, jog cancel): ignored
            elif len(self._rx) < self.rx_capacity:
                self._rx.append(b)
                self.rx_bytes += 1
            else:
                self.rx_dropped += 1      # overflow: the byte is lost, as on the real controller
        self._rx_event.set()

    @property
    def rx_fill(self) -> int:
        return len(self._rx)

    # -- output -----------------------------------------------------------------------------
    def _send(self, line: str) -> None:
        if self._write is not None:
            self._write(line.encode("ascii") + b"\r\n")

    # -- state ------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._current() is not None

    def _current(self) -> Block | None:
        for b in self._queue:
            if b.motion:
                return b
        return None

    @property
    def state(self) -> str:
        if self.alarm:
            return "Alarm"
        if self.homing:
            return "Home"
        if self.hold:
            return f"Hold:{self.hold_sub}"
        if self._current() is not None:
            return "Run"
        return "Idle"

    def status(self) -> GrblStatus:
        st = self.state
        name, _, sub = st.partition(":")
        cur = self._current()
        moving = cur is not None and not (self.hold and self.hold_sub == 0) and not self.alarm
        feed = cur.feed if moving and cur is not None else 0.0
        s = self.spindle_s if self.spindle_on else 0.0
        pins = "P" if self.probe_tripped() else ""
        return GrblStatus(state=name, mpos=tuple(self.pos), feed=feed, spindle=s,  # type: ignore[arg-type]
                          probe_tripped=bool(pins), substate=int(sub) if sub else None, pins=pins,
                          accessories="S" if self.spindle_on else "")

    def status_line(self) -> str:
        return format_status(self.status(), report_buffer=bool(int(self.settings[10]) & 2),
                             rx_free=self.rx_capacity + 1 - len(self._rx),
                             planner_free=self.planner_blocks - self._motion_in_queue)

    def probe_tripped(self) -> bool:
        if self.workpiece is None:
            return False
        p = tuple(self.pos)
        if self._latch is not None:
            if math.dist(p[:3], self._latch[:3]) <= self.workpiece.trigger_mm and p[3:] == self._latch[3:]:
                return True
            self._latch = None
        return self.workpiece.inside(p[:3], p[3], p[4])

    def _notify(self) -> None:
        ev, self._changed = self._changed, asyncio.Event()
        ev.set()

    async def _wait_for(self, pred: Callable[[], bool]) -> None:
        while not pred():
            await self._changed.wait()

    # -- real-time commands -----------------------------------------------------------------
    def _feed_hold(self) -> None:
        if self.alarm or self.homing or self.hold:
            return
        self.hold = True
        cur = self._current()
        if cur is not None and cur.started:
            accel = float(self.settings[120])
            self._hold_v = cur.feed / 60.0
            self._hold_t = self.clock.now()
            self._hold_decel = self._hold_v / accel
            self.hold_sub = 1           # decelerating
        else:
            self.hold_sub = 0           # hold complete, ready to resume
        self._notify()

    def _cycle_start(self) -> None:
        if self.hold and not self.alarm:
            self.hold = False
            self.hold_sub = 0
            self._hold_t = None
            self._work.set()
            self._notify()

    def soft_reset(self) -> None:
        """0x18: abort everything, flush buffers, re-banner (ALARM:3 when reset in motion)."""
        moving = (self._current() is not None and not (self.hold and self.hold_sub == 0)) or self.homing
        code = 6 if self.homing else 3
        if self._proto is not None:
            self._proto.cancel()
        self._rx.clear()
        self._line, self._overflow, self._comment = [], False, 0
        for b in self._queue:
            b.done = True
        self._queue.clear()
        self._motion_in_queue = 0
        if self.world is not None:
            self.world.motion_stopped(DEVICE)
        self.hold = False
        self.hold_sub = 0
        self.homing = False
        self.spindle_on = False
        self._reset_modal()
        self._gc_pos = list(self.pos)
        if moving:
            self.alarm = True
            self.homed = False
            self._send(f"ALARM:{code}")
        self._send("")
        self._send(BANNER)
        if self.alarm:
            self._send("[MSG:'$H'|'$X' to unlock]")
        self._notify()
        if self._proto is not None:
            self._proto = asyncio.get_running_loop().create_task(self._protocol_loop())

    def _raise_alarm(self, code: int) -> None:
        self.alarm = True
        self._send(f"ALARM:{code}")
        if self.world is not None:
            self.world.motion_stopped(DEVICE)

    # -- protocol: lines out of the RX ring -------------------------------------------------
    async def _protocol_loop(self) -> None:
        while True:
            if self.hung:   # the main loop stuck: nothing read, real-time '?' still answered
                await asyncio.sleep(0.05)
                continue
            if not self._rx:
                self._rx_event.clear()
                await self._rx_event.wait()
                continue
            c = chr(self._rx.pop(0))
            if c in "\r\n":
                line, overflow = "".join(self._line), self._overflow
                self._line, self._overflow, self._comment = [], False, 0
                if overflow:
                    self._send("error:11")
                elif not line:
                    self._send("ok")      # empty or comment-only line: grbl acknowledges it
                else:
                    await self._execute(line)
                continue
            if self._comment == 1:
                if c == ")":
                    self._comment = 0
                continue
            if self._comment == 2:
                continue
            if c == "(":
                self._comment = 1
            elif c == ";":
                self._comment = 2
            elif c in " \t%" or ord(c) < 0x20:
                pass
            elif len(self._line) >= LINE_BUFFER_SIZE - 1:
                self._overflow = True
            else:
                self._line.append(c.upper())

    async def _execute(self, line: str) -> None:
        try:
            if line.startswith("$"):
                out = await self._system(line)
            else:
                self.lines_received += 1
                if self.alarm:
                    raise GrblError(9)
                out = await self._gcode(line)
        except GrblError as exc:
            self._send(f"error:{exc.code}")
            return
        for o in out:
            self._send(o)
        self._send("ok")

    # -- $ system commands ------------------------------------------------------------------
    async def _system(self, line: str) -> list[str]:
        idle_or_alarm = self.state in ("Idle", "Alarm")
        if line == "$":
            return ["[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"]
        if line == "$$":
            if not idle_or_alarm:
                raise GrblError(8)
            return [f"${n}={int(v) if n in _INT_SETTINGS else f'{v:.3f}'}" for n, v in self.settings.items()]
        if line == "$#":
            z = ",".join(fmt(0.0) for _ in range(5))
            out = [f"[{g}:{z}]" for g in ("G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92")]
            out += ["[TLO:0.000]", format_probe(self.probe_pos, self.probe_ok)]
            return out
        if line == "$G":
            return ["[GC:" + " ".join([
                self.motion_mode, "G54", "G17", "G20" if self.inches else "G21",
                "G90" if self.absolute else "G91", "G94", "M3" if self.spindle_on else "M5", "M9", "T0",
                f"F{self.feed_rate:.0f}", f"S{self.s_word:.0f}"]) + "]"]
        if line == "$I":
            return [f"[VER:{VERSION}.20190825:5-axis XYZAB (cell simulator)]", "[OPT:VNM,15,128]", "[AXS:5:XYZAB]"]
        if line == "$N":
            return ["$N0=", "$N1="]
        if line == "$X":
            if not idle_or_alarm:
                raise GrblError(8)
            if self.alarm:
                self.alarm = False
                self._notify()
                return ["[MSG:Caution: Unlocked]"]
            return []
        if line == "$H":
            if not self.settings[22]:
                raise GrblError(5)
            if not idle_or_alarm:
                raise GrblError(8)
            await self._home()
            return []
        m = re.fullmatch(r"\$(\d+)=(.*)", line)
        if m:
            if not idle_or_alarm:
                raise GrblError(8)
            n = int(m.group(1))
            if n not in self.settings:
                raise GrblError(3)
            if not _NUM.fullmatch(m.group(2)):
                raise GrblError(2)
            v = float(m.group(2))
            if v < 0:
                raise GrblError(4)
            self.settings[n] = int(v) if n in _INT_SETTINGS else v
            return []
        raise GrblError(3)

    async def _home(self) -> None:
        self.homing = True
        self._notify()
        dist = max(abs(a - b) for a, b in zip(self.pos, self.home))
        seek = float(self.settings[25]) / 60.0
        await asyncio.sleep(self.clock.wall(dist / seek + 2 * float(self.settings[27]) / seek))
        self.pos = list(self.home)
        self._gc_pos = list(self.pos)
        self._latch = None
        self.homing = False
        self.alarm = False
        self.homed = True
        self._notify()

    # -- G-code -----------------------------------------------------------------------------
    async def _gcode(self, line: str) -> list[str]:
        words: dict[str, float] = {}
        gs: list[float] = []
        ms: list[int] = []
        i = 0
        while i < len(line):
            letter = line[i]
            if not "A" <= letter <= "Z":
                raise GrblError(1)
            m = _NUM.match(line, i + 1)
            if m is None:
                raise GrblError(2)
            val = float(m.group(0))
            i = m.end()
            if letter == "G":
                gs.append(val)
            elif letter == "M":
                if val != int(val):
                    raise GrblError(20)
                ms.append(int(val))
            else:
                if letter in words:
                    raise GrblError(25)
                words[letter] = val
        nline = words.pop("N", None)
        seq = int(nline) if nline is not None else self.lines_received

        motion: str | None = None
        dwell = machine = False
        inverse = self.inverse_time
        absolute, inches = self.absolute, self.inches
        for g in gs:
            code = round(g, 1)
            if code in (0, 1, 38.2, 38.3, 80):
                if motion is not None:
                    raise GrblError(21)
                motion = {0: "G0", 1: "G1", 38.2: "G38.2", 38.3: "G38.3", 80: "G80"}[code]
            elif code == 4:
                dwell = True
            elif code == 53:
                machine = True
            elif code in (90, 91):
                absolute = code == 90
            elif code in (20, 21):
                inches = code == 20
            elif code in (93, 94):
                inverse = code == 93
            elif code in (17, 40, 49, 54, 55, 56, 57, 58, 59, 61, 91.1):
                pass  # accepted; the simulator keeps G54 with zero offsets
            else:
                raise GrblError(20)  # arcs, G10/G28/G30/G92, G38.4/5: not simulated
        spindle: bool | None = None
        for mc in ms:
            if mc in (3, 4):
                spindle = True
            elif mc == 5:
                spindle = False
            elif mc in (0, 1, 2, 30, 7, 8, 9):
                pass
            else:
                raise GrblError(20)
        for letter in words:
            if letter not in self.letters + "FSPT":
                raise GrblError(20)
        if "F" in words and words["F"] < 0 or "S" in words and words["S"] < 0:
            raise GrblError(4)
        if "P" in words and not dwell:
            raise GrblError(36)
        if dwell and "P" not in words:
            raise GrblError(28)

        # modal updates, in grbl's order of execution
        self.absolute, self.inches = absolute, inches
        if inverse != self.inverse_time:
            self.inverse_time = inverse
            self.feed_rate = 0.0  # grbl: switching feed modes leaves the feed undefined
        unit = 25.4 if inches else 1.0
        if "F" in words:
            self.feed_rate = words["F"] * (1.0 if inverse else unit)
        if "S" in words:
            self.s_word = words["S"]
        if motion is not None:
            self.motion_mode = motion
        axes = {k: v for k, v in words.items() if k in self.letters}
        mode = self.motion_mode
        if spindle is not None:
            self._push(Block(seq, "M3" if spindle else "M5", line, s=self.s_word, spindle=spindle))
        if dwell:
            await self._sync()
            await asyncio.sleep(self.clock.wall(max(words["P"], 0.0)))
            self._log_block(Block(seq, "G4", line), self.clock.now())
        if axes:
            if mode == "G80":
                raise GrblError(31)
            target = list(self._gc_pos)
            for k, v in axes.items():
                j = self.letters.index(k)
                v = v * unit if j < 3 else v
                target[j] = v if (absolute or machine) else target[j] + v
            tgt = tuple(target)
            if mode.startswith("G38"):
                return await self._probe(seq, mode, line, tgt)  # type: ignore[arg-type]
            if mode == "G1":
                if self.feed_rate <= 0 or (self.inverse_time and "F" not in words):
                    raise GrblError(22)  # G93: every G1 carries its own F
                feed = self.feed_rate
                if self.inverse_time:  # F = 1/minutes for the move: the rate along the 5-D path
                    feed = math.dist(tgt, self._gc_pos) * self.feed_rate
            else:
                moving = [j for j in range(5) if abs(tgt[j] - self._gc_pos[j]) > 1e-9]
                feed = min((float(self.settings[110 + j]) for j in moving), default=float(self.settings[110]))
            await self._wait_for(lambda: self._motion_in_queue < self.planner_blocks)
            self._push(Block(seq, mode, line, target=tgt, feed=feed, s=self.s_word))  # type: ignore[arg-type]
            self._gc_pos = list(tgt)
        elif motion is not None and motion.startswith("G38"):
            raise GrblError(26)
        elif spindle is None and not dwell:
            self._push(Block(seq, motion or ("F" if "F" in words else "G"), line))  # modal-only: logged in order
        return []

    def _push(self, b: Block) -> None:
        if b.motion:
            self._motion_in_queue += 1
        self._queue.append(b)
        self._work.set()

    async def _sync(self) -> None:
        """Wait until every queued block has executed (grbl's protocol_buffer_synchronize)."""
        await self._wait_for(lambda: not self._queue)

    async def _probe(self, seq: int, mode: str, line: str, target: Pos5) -> list[str]:
        if self.feed_rate <= 0:
            raise GrblError(22)
        await self._sync()
        if all(abs(a - b) < 1e-9 for a, b in zip(target[:3], self.pos[:3])):
            raise GrblError(33)
        if self.probe_tripped():
            self._raise_alarm(4)
            self._notify()
            return []
        b = Block(seq, mode, line, target=target, feed=self.feed_rate, s=self.s_word, probe=mode)
        self._push(b)
        await self._wait_for(lambda: b.done)
        self._gc_pos = list(self.pos)
        self.probe_pos = tuple(self.pos)  # type: ignore[assignment]
        self.probe_ok = b.contact
        if not b.contact and mode == "G38.2":
            self._raise_alarm(5)
        return [format_probe(self.probe_pos, b.contact)]

    # -- execution --------------------------------------------------------------------------
    def _log_block(self, b: Block, t: float) -> None:
        self.executed.append(b)
        self.executed_count += 1
        if self._log is not None:
            self._log.write(json.dumps({"seq": b.seq, "verb": b.verb, "target": [round(v, 4) for v in self.pos[:3]],
                                        "t": round(t, 4), "line": b.line}) + "\n")
            self._log_dirty = True

    def _finish(self, b: Block, t: float) -> None:
        self._queue.popleft()
        b.done = True
        if b.motion:
            self._motion_in_queue -= 1
            if self.world is not None:
                self.world.motion_stopped(DEVICE)
        self._log_block(b, t)
        if not any(x.motion for x in self._queue) and self._rx:
            self.starved += 1
        self._notify()

    def _start_probe(self, b: Block) -> None:
        """At the start of a probing move: cut it short where the stylus will touch the part."""
        if self.workpiece is None:
            return
        hit = self.workpiece.probe(self.pos[:3], b.target[:3], self.pos[3], self.pos[4])  # type: ignore[index]
        if hit is not None:
            b.target = (hit[0], hit[1], hit[2], self.pos[3], self.pos[4])
            b.contact = True

    def advance(self, t: float, now: float) -> None:
        """Execute queued blocks over simulated time [t, now]."""
        if self.freeze is not None and (time.monotonic() - self._t0 if self.freeze[0] == "t"
                                        else self.executed_count) >= self.freeze[1]:
            return  # fault: reports Run with lines queued, never moves
        while t < now and self._queue and not self.alarm and not (self.hold and self.hold_sub == 0):
            b = self._queue[0]
            if not b.motion:
                if b.spindle is not None:
                    self.spindle_on = b.spindle
                    self.spindle_s = b.s
                self._finish(b, t)
                continue
            if not b.started:
                b.started = True
                if b.probe:
                    self._start_probe(b)
            if self.spindle_on:
                self.spindle_s = b.s  # laser mode: S changes apply in motion
            p0 = tuple(self.pos)
            delta = [e - s for s, e in zip(p0, b.target)]  # type: ignore[arg-type]
            dist = math.sqrt(sum(d * d for d in delta))
            v = max(b.feed, 1e-6) / 60.0
            if self.hold:  # decelerating to a stop (Hold:1): speed falls linearly to 0
                th, dec = self._hold_t or t, max(self._hold_decel, 1e-9)
                a0, a1 = max(t - th, 0.0), min(now - th, dec)
                travel = self._hold_v * ((a1 - a0) - (a1 * a1 - a0 * a0) / (2 * dec)) if a1 > a0 else 0.0
                stop = now - th >= dec
                if travel >= dist:
                    p1, t1 = b.target, now
                else:
                    f = travel / dist if dist > 0 else 0.0
                    p1, t1 = tuple(a + f * d for a, d in zip(p0, delta)), now
                self._moved(b, p0, p1, t, t1)
                if travel >= dist:
                    self._finish(b, t1)
                if stop:
                    self.hold_sub = 0
                    if self.world is not None:
                        self.world.motion_stopped(DEVICE)
                    self._notify()
                break
            need = dist / v
            if t + need <= now:
                self._moved(b, p0, b.target, t, t + need)  # type: ignore[arg-type]
                t += need
                if b.probe:
                    self._latch = tuple(self.pos) if b.contact else None
                self._finish(b, t)
                continue
            f = (now - t) * v / dist
            self._moved(b, p0, tuple(a + f * d for a, d in zip(p0, delta)), t, now)
            break
        if self.hold and self.hold_sub == 1 and not self._current():
            self.hold_sub = 0
            self._notify()

    def _moved(self, b: Block, p0: tuple, p1: tuple, t0: float, t1: float) -> None:
        self.pos = list(p1)
        if self.world is not None and p0 != p1:
            part = None
            if self.workpiece is not None:  # the segment on the part, from the sim's own true pose
                q0, _ = self.workpiece.part_frame(p0)
                q1, ax = self.workpiece.part_frame(p1)
                part = (tuple(q0), tuple(q1), tuple(ax))
            self.world.torch_moved(DEVICE, b.seq, tuple(p0[:3]), tuple(p1[:3]), t0, t1, part=part)

    async def _exec_loop(self) -> None:
        last = self.clock.now()
        while True:
            if not self._queue or self.alarm or (self.hold and self.hold_sub == 0):  # nothing can move
                if self._log_dirty and self._log is not None:
                    self._log.flush()
                    self._log_dirty = False
                self._work.clear()
                await self._work.wait()
                last = self.clock.now()
            await asyncio.sleep(self.tick_s)
            now = self.clock.now()
            self.advance(last, now)
            last = now
            if self._log_dirty and self._log is not None and not self._queue:
                self._log.flush()
                self._log_dirty = False


async def serve(ctx) -> list:
    """Start the CNC simulator on cell.yaml's cnc URL (or port 0 / a pty), per ctx."""
    dev = ctx.cell.devices.cnc
    spec = parse_fault_spec(ctx.faults)
    wp = Workpiece.from_config(ctx.sim.cnc.workpiece, ctx.sim.cnc.probe_noise_mm, seed=spec.seed,
                               kinematics=ctx.cell.kinematics, base_dir=ctx.config_dir)
    sim = CncSim(clock=ctx.clock, world=ctx.world, workpiece=wp, rx_buffer_bytes=dev.rx_buffer_bytes,
                 letters=wp.kin.letters,
                 log_path=(Path(ctx.log_dir) / "cnc.jsonl") if ctx.log_dir else None)
    for cond, v in spec.events("freeze"):
        sim.freeze = (cond, float(v))
    if "freeze" in spec.values:
        sim.freeze = ("t", 0.0)
    use_deposit_map(ctx, wp)
    return await serve_serial(sim, DEVICE, dev, ctx, spec, {"protocol": "grbl 1.1"})


def use_deposit_map(ctx: Any, wp: Workpiece) -> None:
    """Metal the CNC deposits is the World's height map in the workpiece frame (its substrate the
    workpiece mesh): the touch probe reads it, so probing after a repair sees the deposit."""
    phys = attach(ctx)
    if phys is None:
        return
    phys.set_substrate(DEVICE, wp.top_z)
    wp.deposit_map = phys.height_map(DEVICE)

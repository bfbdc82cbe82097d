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
import time
from collections import deque
from pathlib import Path
from typing import IO, TYPE_CHECKING, Callable


from wire.grbl_protocol import GrblStatus, format_status
from sims.clock import SimClock
from sims.cnc_block import DEVICE, Block, GrblError, Pos5, pos5
from sims.cnc_gcode import run_gcode
from sims.cnc_motion import move_block
from sims.cnc_freeze import Freeze
from sims.cnc_system import DEFAULT_SETTINGS, VERSION, system_command
from sims.faults import parse_fault_spec
from sims.cnc_cut import Breakage, Spindle, sim_tools, use_deposit_map
from sims.transport import SerialServer, serve_serial
from sims.workpiece import Workpiece
from sims.world import World

if TYPE_CHECKING:
    from core.tools import Tools
    from sims.up import Served, SimContext

BANNER = f"Grbl {VERSION} ['$' for help]"
LINE_BUFFER_SIZE = 80     # grbl: at most 79 characters per line after stripping
PLANNER_BLOCKS = 15       # grbl 1.1 on a 328p: BLOCK_BUFFER_SIZE 16, one kept free


class CncSim:
    """In-process grbl 1.1 controller. Drive it with attach/feed/detach (sims.transport.ByteSim)."""

    WORK_BUDGET_S = 0.003   # wall time a tick may spend laying the World's deferred beads (RobotSim's)

    def __init__(self, *, clock: SimClock, world: World | None = None, workpiece: Workpiece | None = None,
                 log_path: str | Path | None = None, rx_buffer_bytes: int = 128,
                 planner_blocks: int = PLANNER_BLOCKS, homing_enabled: bool = True,
                 home: Pos5 | None = None, tick_s: float = 0.002, letters: str = "XYZAB",
                 tools: Tools | None = None) -> None:
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
        self.freeze = Freeze(self)   # fault `freeze@t=`/`@move=`/...: Run, no motion (sims/cnc_freeze.py)
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
        self._proto: asyncio.Task[None] | None = None
        self._exec: asyncio.Task[None] | None = None
        self._log: IO[str] | None = None
        self._log_dirty = False
        self.server: SerialServer | None = None   # set by serve_serial (tests pull the cable)
        if log_path is not None:
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            self._log = open(log_path, "a", encoding="utf-8")
        self.tlo = 0.0   # G43.1 Z: the tool length offset in effect
        self.spindle = Spindle(sim_tools(tools), workpiece, Path(log_path).parent / "cut.jsonl" if log_path else None,
                               tools.setter_mm if tools is not None else (-150.0, -150.0, 0.0))

    def _default_home(self) -> Pos5:
        # Parked 50 mm above the workpiece's highest point (rounded up to 10 mm), so the probe
        # is clear of the part after power-up and after homing.
        top = 0.0
        if self.workpiece is not None:
            m = self.workpiece.part_to_machine()
            top = max(float((self.workpiece.vertices() @ m[:3, :3].T + m[:3, 3])[:, 2].max()), 0.0)
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
        self.spindle.close()

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
        return GrblStatus(state=name, mpos=pos5(self.pos), feed=feed, spindle=s,
                          probe_tripped=bool(pins), substate=int(sub) if sub else None, pins=pins,
                          accessories="S" if self.spindle_on else "")

    def status_line(self) -> str:
        return format_status(self.status(), report_buffer=bool(int(self.settings[10]) & 2),
                             rx_free=self.rx_capacity + 1 - len(self._rx),
                             planner_free=self.planner_blocks - self._motion_in_queue)

    def probe_tripped(self) -> bool:
        if self.workpiece is None or self.spindle.is_cutter:
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
                out = await system_command(self, line)
            else:
                self.lines_received += 1
                if self.alarm:
                    raise GrblError(9)
                out = await run_gcode(self, line)
        except GrblError as exc:
            self._send(f"error:{exc.code}")
            return
        for o in out:
            self._send(o)
        self._send("ok")

    # -- $ system commands: sims/cnc_system.py ---------------------------------------------
    async def _home(self) -> None:
        self.homing = True
        self._notify()
        if self.freeze.homing():
            await asyncio.Event().wait()   # fault: the homing cycle never finishes (a reset ends it)
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

    # -- G-code: sims/cnc_gcode.py ----------------------------------------------------------
    def _push(self, b: Block) -> None:
        if b.motion:
            self._motion_in_queue += 1
        self._queue.append(b)
        self._work.set()

    async def _sync(self) -> None:
        """Wait until every queued block has executed (grbl's protocol_buffer_synchronize)."""
        await self._wait_for(lambda: not self._queue)

    # -- execution --------------------------------------------------------------------------
    def _log_block(self, b: Block, t: float) -> None:
        self.executed.append(b)
        self.executed_count += 1
        if self._log is not None:
            self._log.write(json.dumps({"seq": b.seq, "verb": b.verb, "target": [round(v, 4) for v in self.pos[:3]],
                                        "t": round(t, 4), "line": b.line}) + "\n")
            self._log_dirty = True

    def _finish(self, b: Block, t: float) -> None:
        if not self._queue or self._queue[0] is not b:   # flushed by an alarm while it moved
            b.done = True
            return
        self._queue.popleft()
        self.spindle.finished(b, t)
        b.done = True
        if b.motion:
            self._motion_in_queue -= 1
            if self.world is not None:
                self.world.motion_stopped(DEVICE)
        self._log_block(b, t)
        if not any(x.motion for x in self._queue) and self._rx:
            self.starved += 1
        self._notify()

    def advance(self, t: float, now: float) -> None:
        """Execute queued blocks over simulated time [t, now] (every block due: grbl's planner has its own CPU)."""
        if self.freeze.on(self._current()):
            return  # fault: reports Run with lines queued, never moves
        while t < now and self._queue and not self.alarm and not (self.hold and self.hold_sub == 0):
            b = self._queue[0]
            if b.target is None:
                if b.spindle is not None:
                    self.spindle_on = b.spindle
                    self.spindle_s = b.s
                self._finish(b, t)
                if b.verb == "M0":   # program pause: Hold:0 until `~`; the operator changes the tool
                    self.hold, self.hold_sub = True, 0
                    self.spindle.load_selected()
                    self._notify()
                continue
            if self.freeze.starting(b):
                return   # the travel or probing move of `freeze@travel/probe=N` never starts
            done = move_block(self, b, b.target, t, now)
            if done is None:
                break
            t = done
        if self.hold and self.hold_sub == 1 and not self._current():
            self.hold_sub = 0
            self._notify()

    def _moved(self, b: Block, p0: Pos5, p1: Pos5, t0: float, t1: float) -> None:
        self.pos = list(p1)
        try:   # laser mode ($32=1) stops the spindle on rapids
            self.spindle.moved(b, p0, p1, self.spindle_on and self.spindle_s > 0
                               and not (int(self.settings[32]) and b.verb == "G0"), self.spindle_s)
        except Breakage as exc:
            self._send(f"[MSG:Tool breakage: {exc}]")
            self._queue.clear()
            self._motion_in_queue = 0
            self.spindle_on = False
            self.homed = False
            self._raise_alarm(1)
            self._notify()
        if self.world is not None and p0 != p1:
            part = None
            if self.workpiece is not None:  # the segment on the part, from the sim's own true pose
                q0, _ = self.workpiece.part_frame(p0)
                q1, ax = self.workpiece.part_frame(p1)
                part = (tuple(q0), tuple(q1), tuple(ax))
            self.world.torch_moved(DEVICE, b.seq, p0[:3], p1[:3], t0, t1, part=part)

    async def _exec_loop(self) -> None:
        last = self.clock.now()
        while True:
            if not self._queue or self.alarm or (self.hold and self.hold_sub == 0):  # nothing can move
                if self._log_dirty and self._log is not None:
                    self._log.flush()
                    self._log_dirty = False
                self._work.clear()
                while self.world is not None and not self.world.settle(time.perf_counter() + self.WORK_BUDGET_S):
                    await asyncio.sleep(0.001)   # deferred beads: a slice, a rest (RobotSim.LAY_REST_S)
                await self._work.wait()
                last = self.clock.now()
            await asyncio.sleep(self.tick_s)
            now = self.clock.now()
            self.advance(last, now)
            last = now
            if self.world is not None:   # deferred beads, within the budget
                self.world.settle(time.perf_counter() + self.WORK_BUDGET_S)
            if self._log_dirty and self._log is not None and not self._queue:
                self._log.flush()
                self._log_dirty = False


async def serve(ctx: SimContext) -> list[Served]:
    """Start the CNC simulator on cell.yaml's cnc URL (or port 0 / a pty), per ctx."""
    dev = ctx.cell.devices.cnc
    spec = parse_fault_spec(ctx.faults)
    wp = Workpiece.from_config(ctx.sim.cnc.workpiece, ctx.sim.cnc.probe_noise_mm, seed=spec.seed,
                               kinematics=ctx.cell.kinematics, base_dir=ctx.config_dir)
    sim = CncSim(clock=ctx.clock, world=ctx.world, workpiece=wp, rx_buffer_bytes=dev.rx_buffer_bytes,
                 letters=wp.kin.letters, tools=ctx.cell.tools, log_path=(Path(ctx.log_dir) / "cnc.jsonl") if ctx.log_dir else None)
    for cond, v in spec.events("freeze"):
        sim.freeze.when = (cond, float(v))
    if "freeze" in spec.values:
        sim.freeze.when = ("t", 0.0)
    use_deposit_map(ctx, wp)
    return await serve_serial(sim, DEVICE, dev, ctx, spec, {"protocol": "grbl 1.1"})


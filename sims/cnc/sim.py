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


from sims.clock import SimClock
from sims.context import Served, SimContext
from sims.cnc.block import DEVICE, Block, GrblError, Pos5, pos5
from sims.cnc.cut import Spindle, sim_tools, use_deposit_map
from sims.cnc.freeze import Freeze
from sims.cnc.gcode import run_gcode
from sims.cnc.laser import process_power
from sims.cnc.motion import finish, move_block
from sims.cnc.state import CncState
from sims.cnc.system import DEFAULT_SETTINGS, VERSION, system_command
from sims.faults import parse_fault_spec
from sims.transport import SerialServer, serve_serial
from sims.workpiece import Workpiece
from sims.world import World
from wire.grbl_protocol import GrblStatus, format_status

if TYPE_CHECKING:
    from core.tools import Tools

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
        self.world = world
        self.workpiece = workpiece
        self.tick_s = tick_s
        self.rx_capacity = rx_buffer_bytes - 1  # a ring buffer of N bytes holds N-1
        settings = dict(DEFAULT_SETTINGS)
        settings[22] = 1 if homing_enabled else 0
        park = home if home is not None else self._default_home()
        # powered up where it was parked; HOMING_INIT_LOCK: locked until $H / $X
        self.machine = CncState(letters=letters, settings=settings, planner_blocks=planner_blocks, home=park,
                                pos=list(park), gc_pos=list(park), alarm=bool(settings[22]))
        # counters for tests and benchmarks
        self.rx_dropped = 0
        self.rx_bytes = 0
        self.executed: deque[Block] = deque(maxlen=10_000)   # the most recent executed lines
        self.executed_count = 0
        self.starved = 0          # times the planner ran empty while lines were still arriving
        self._rx = bytearray()
        self.hung = False    # a firmware whose main loop stopped reading its input (tests set it)
        self.freeze = Freeze(lambda: self.executed_count)   # fault `freeze@t=`/`@move=`/...: Run, no motion (freeze.py)
        self._t0 = time.monotonic()
        self._line: list[str] = []
        self._overflow = False
        self._comment = 0
        self._write: Callable[[bytes], None] | None = None
        self._rx_event = asyncio.Event()
        self._proto: asyncio.Task[None] | None = None
        self._exec: asyncio.Task[None] | None = None
        self._log: IO[str] | None = None
        self._log_dirty = False
        self.server: SerialServer | None = None   # set by serve_serial (tests pull the cable)
        if log_path is not None:
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            self._log = open(log_path, "a", encoding="utf-8")
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
                self.send(self.status_line())
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
    def send(self, line: str) -> None:
        if self._write is not None:
            self._write(line.encode("ascii") + b"\r\n")

    # -- state ------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.machine.current() is not None

    @property
    def state(self) -> str:
        if self.machine.alarm:
            return "Alarm"
        if self.machine.homing:
            return "Home"
        if self.machine.hold:
            return f"Hold:{self.machine.hold_sub}"
        if self.machine.current() is not None:
            return "Run"
        return "Idle"

    def status(self) -> GrblStatus:
        st = self.state
        name, _, sub = st.partition(":")
        cur = self.machine.current()
        moving = cur is not None and not (self.machine.hold and self.machine.hold_sub == 0) and not self.machine.alarm
        feed = cur.feed if moving and cur is not None else 0.0
        s = process_power(self.machine, cur if moving else None)
        pins = "P" if self.probe_tripped() else ""
        return GrblStatus(state=name, mpos=pos5(self.machine.pos), feed=feed, spindle=s,
                          probe_tripped=bool(pins), substate=int(sub) if sub else None, pins=pins,
                          accessories=("C" if self.machine.spindle_ccw else "S") if self.machine.spindle_on else "")

    def status_line(self) -> str:
        return format_status(self.status(), report_buffer=bool(int(self.machine.settings[10]) & 2),
                             rx_free=self.rx_capacity + 1 - len(self._rx),
                             planner_free=self.machine.planner_blocks - self.machine.motion_in_queue)

    def probe_tripped(self) -> bool:
        if self.workpiece is None or self.spindle.is_cutter:
            return False
        p = tuple(self.machine.pos)
        if self.machine.latch is not None:
            if math.dist(p[:3], self.machine.latch[:3]) <= self.workpiece.trigger_mm and p[3:] == self.machine.latch[3:]:
                return True
            self.machine.latch = None
        return self.workpiece.inside(p[:3], p[3], p[4])

    # -- real-time commands -----------------------------------------------------------------
    def _feed_hold(self) -> None:
        if self.machine.alarm or self.machine.homing or self.machine.hold:
            return
        self.machine.hold = True
        cur = self.machine.current()
        if cur is not None and cur.started:
            accel = float(self.machine.settings[120])
            self.machine.hold_v = cur.feed / 60.0
            self.machine.hold_t = self.clock.now()
            self.machine.hold_decel = self.machine.hold_v / accel
            self.machine.hold_sub = 1           # decelerating
        else:
            self.machine.hold_sub = 0           # hold complete, ready to resume
        self.machine.notify()

    def _cycle_start(self) -> None:
        if self.machine.hold and not self.machine.alarm:
            self.machine.hold = False
            self.machine.hold_sub = 0
            self.machine.hold_t = None
            self.machine.work.set()
            self.machine.notify()

    def soft_reset(self) -> None:
        """0x18: abort everything, flush buffers, re-banner (ALARM:3 when reset in motion)."""
        moving = (self.machine.current() is not None and not (self.machine.hold and self.machine.hold_sub == 0)) or self.machine.homing
        code = 6 if self.machine.homing else 3
        if self._proto is not None:
            self._proto.cancel()
        self._rx.clear()
        self._line, self._overflow, self._comment = [], False, 0
        for b in self.machine.queue:
            b.done = True
        self.machine.queue.clear()
        self.machine.motion_in_queue = 0
        if self.world is not None:
            self.world.motion_stopped(DEVICE)
        self.machine.hold = False
        self.machine.hold_sub = 0
        self.machine.homing = False
        self.machine.spindle_on = self.machine.spindle_ccw = False
        self.machine.reset_modal()
        self.machine.gc_pos = list(self.machine.pos)
        if moving:
            self.machine.alarm = True
            self.machine.homed = False
            self.send(f"ALARM:{code}")
        self.send("")
        self.send(BANNER)
        if self.machine.alarm:
            self.send("[MSG:'$H'|'$X' to unlock]")
        self.machine.notify()
        if self._proto is not None:
            self._proto = asyncio.get_running_loop().create_task(self._protocol_loop())

    def raise_alarm(self, code: int) -> None:
        self.machine.alarm = True
        self.send(f"ALARM:{code}")
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
                    self.send("error:11")
                elif not line:
                    self.send("ok")      # empty or comment-only line: grbl acknowledges it
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
                self.machine.lines_received += 1
                if self.machine.alarm:
                    raise GrblError(9)
                out = await run_gcode(self, line)
        except GrblError as exc:
            self.send(f"error:{exc.code}")
            return
        for o in out:
            self.send(o)
        self.send("ok")

    # -- $ system commands: system.py --------------------------------------------------------
    async def run_homing(self) -> None:
        self.machine.homing = True
        self.machine.notify()
        if self.freeze.homing():
            await asyncio.Event().wait()   # fault: the homing cycle never finishes (a reset ends it)
        dist = max(abs(a - b) for a, b in zip(self.machine.pos, self.machine.home))
        seek = float(self.machine.settings[25]) / 60.0
        await asyncio.sleep(self.clock.wall(dist / seek + 2 * float(self.machine.settings[27]) / seek))
        self.machine.pos = list(self.machine.home)
        self.machine.gc_pos = list(self.machine.pos)
        self.machine.latch = None
        self.machine.homing = False
        self.machine.alarm = False
        self.machine.homed = True
        if self._log is not None:   # the homing cycle in the execution log, when it ended (cnc.jsonl)
            self._log.write(json.dumps({"seq": 0, "verb": "$H", "target": [round(v, 4) for v in self.machine.pos[:3]],
                                        "t": round(self.clock.now(), 4), "line": "$H"}) + "\n")
            self._log_dirty = True
        self.machine.notify()

    # -- execution (motion.py moves a block; gcode.py queues them) ---------------------------
    def log_block(self, b: Block, t: float) -> None:
        self.executed.append(b)
        self.executed_count += 1
        if self._log is not None:
            self._log.write(json.dumps({"seq": b.seq, "verb": b.verb, "target": [round(v, 4) for v in self.machine.pos[:3]],
                                        "t": round(t, 4), "line": b.line}) + "\n")
            self._log_dirty = True

    def flush_log(self) -> None:
        """Write the execution log (`cnc.jsonl`) out now (the executor flushes it when idle)."""
        if self._log is not None:
            self._log.flush()

    def advance(self, t: float, now: float) -> None:
        """Execute queued blocks over simulated time [t, now] (every block due: grbl's planner has its own CPU)."""
        if self.freeze.on(self.machine.current()):
            return  # fault: reports Run with lines queued, never moves
        while t < now and self.machine.queue and not self.machine.alarm and not (self.machine.hold and self.machine.hold_sub == 0):
            b = self.machine.queue[0]
            if b.target is None:
                if b.spindle is not None:
                    self.machine.spindle_on, self.machine.spindle_ccw = b.spindle, b.ccw
                    self.machine.spindle_s = b.s
                finish(self, b, t)
                if b.verb == "M0":   # program pause: Hold:0 until `~`; the operator changes the tool
                    self.machine.hold, self.machine.hold_sub = True, 0
                    self.spindle.load_selected()
                    self.machine.notify()
                continue
            if self.freeze.starting(b):
                return   # the travel or probing move of `freeze@travel/probe=N` never starts
            done = move_block(self, b, b.target, t, now)
            if done is None:
                break
            t = done
        if self.machine.hold and self.machine.hold_sub == 1 and not self.machine.current():
            self.machine.hold_sub = 0
            self.machine.notify()

    async def _exec_loop(self) -> None:
        last = self.clock.now()
        while True:
            if not self.machine.queue or self.machine.alarm or (self.machine.hold and self.machine.hold_sub == 0):  # nothing can move
                if self._log_dirty and self._log is not None:
                    self._log.flush()
                    self._log_dirty = False
                self.machine.work.clear()
                while self.world is not None and not self.world.settle(time.perf_counter() + self.WORK_BUDGET_S):
                    await asyncio.sleep(0.001)   # deferred beads: a slice, a rest (RobotSim.LAY_REST_S)
                await self.machine.work.wait()
                last = self.clock.now()
            await asyncio.sleep(self.tick_s)
            now = self.clock.now()
            self.advance(last, now)
            last = now
            if self.world is not None:   # deferred beads, within the budget
                self.world.settle(time.perf_counter() + self.WORK_BUDGET_S)
            if self._log_dirty and self._log is not None and not self.machine.queue:
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


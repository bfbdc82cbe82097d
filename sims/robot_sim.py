"""Robot simulator: the robot side of RLP/1 and RLP/2 (docs/contract.md §5, docs/protocols/rlp.md).

Checks every frame (CRC, syntax, sequence), keeps a bounded motion queue (RLP/2, once a host asks
for it with `!PROTO 2`: also the frames that arrive beyond a gap, reported by SACK, §9), executes the moves in
simulated time (SimClock) at the commanded speed, answers ACK / NAK / EXE / MRK / ERR / STA and a
heartbeat every second, holds motion after 3 s of silence, reports torch motion to the World and
appends every executed queue entry to `robot.jsonl` ({"seq", "verb", "target", "t"}, §6a). Its
state (queue, last_rx, last_exec, position) survives a host disconnect, as a real controller's
does. Served on loopback TCP or a pty through sims/transport.py.
"""
from __future__ import annotations

import asyncio
import json
import time
from collections import deque
from pathlib import Path
from typing import IO, Callable

from wire import rlp
from sims.clock import SimClock
from sims.faults import FaultSpec, parse_fault_spec
from sims.context import Served, SimContext, attach
from sims.robot_lies import Misbehaviour
from sims.transport import SerialServer, serve_serial
from sims.world import World

DEVICE = "robot"
ERR_WORKSPACE = 10


class RobotSim:
    """In-process robot controller. Drive it with attach/feed/detach (the ByteSim protocol)."""

    IDLE_TICK_S = 0.01  # wall seconds between executor ticks while nothing can move
    MIN_TICK_S = 0.0002
    # Wall time one executor tick may spend on moves before it lets the loop run. Laying the
    # world's bead costs 1-2.5 ms a segment; at time scale 60 a short move lasts 0.3 ms, so a tick
    # that ran every due move at once spiralled (the backlog grew with each tick) and held the
    # simulators' loop for 80 ms: the power source and the cell I/O, separate devices on a real
    # cell, answered nothing meanwhile ("no reply within 50 ms"). Moves left over run on the next
    # tick, at their own simulated times: the robot lags, it never skips.
    WORK_BUDGET_S = 0.003
    # Deferred beads (sims/world.py) are laid in slices of the budget with this rest between them:
    # at the simulators' real-time priority, back-to-back slices would take a whole CPU from the
    # controller (its serial reader stamps the robot's reports: late stamps read as a stand-still).
    LAY_REST_S = 0.001

    def __init__(self, *, clock: SimClock, world: World | None = None, queue_slots: int = 64,
                 log_path: str | Path | None = None, heartbeat_s: float = 1.0,
                 link_timeout_s: float = 3.0,
                 workspace: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
                 home: tuple[float, float, float] = (0.0, 0.0, 0.0), tick_s: float = 0.002,
                 record: bool = False, faults: FaultSpec | None = None,
                 fault_log: str | Path | None = None, line_rate: float | None = None,
                 max_protocol: int = 2) -> None:
        self.clock = clock
        self.world = world
        self.slots = queue_slots
        self.heartbeat_s = heartbeat_s
        self.link_timeout_s = link_timeout_s
        self.workspace = workspace
        self.tick_s = tick_s
        self.pos: tuple[float, float, float] = (float(home[0]), float(home[1]), float(home[2]))
        self.queue: deque[rlp.Move] = deque()
        self.last_rx = 0
        self.last_exec = 0
        self.held = False
        self.silence_held = False
        self.waiting = False
        self.fault = False
        self.discarding = False
        self.max_protocol = max_protocol      # 1: a robot that speaks only RLP/1 (rejects !PROTO)
        self.proto = 1                        # in force on this connection (RLP/1 until a host asks)
        self.ahead: dict[int, rlp.Move] = {}  # RLP/2: frames received beyond a gap, by seq
        self.held_at: float | None = None    # monotonic time of the latest !HOLD (tests: arc first)
        self.executed: list[int] | None = [] if record else None  # wire seqs, in execution order
        # counters
        self.frames_rx = self.crc_errors = self.syntax_errors = self.naks = self.duplicates = 0
        self.executed_count = 0
        self.travels = 0            # travel moves (MOVJ) that came to the head of the queue
        self._head_seen = -1
        self.underruns = 0          # times the queue ran empty after a move (the job's end counts)
        self.hb = 0
        self._write: Callable[[bytes], None] | None = None
        self._splitter = rlp.LineSplitter()
        self._ack_due = False
        self._exe_due: int | None = None
        self._next_finish: float | None = None   # process time the head move ends (while moving)
        self._last_heard = time.monotonic()
        self._log: IO[str] | None = None
        self._log_dirty = False
        self.server: SerialServer | None = None   # set by serve_serial (tests pull the cable)
        if log_path is not None:
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            self._log = open(log_path, "a", encoding="utf-8")
        self._tasks: list[asyncio.Task[None]] = []
        # flood / lie / garble / mute (issue 13): the robot misbehaving on the wire
        self.lies = Misbehaviour(self, faults, fault_log, line_rate)
        # slots a flush leaves taken (fault `phantom`): set by the first !ABORT
        self.phantom_on_abort = int(faults.value("phantom", 0)) if faults is not None else 0
        self.phantom = 0

    # -- lifecycle --------------------------------------------------------------------------------
    def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._exec_loop()), loop.create_task(self._link_loop())]
        if self.lies:
            self._tasks.append(loop.create_task(self.lies.run()))

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except asyncio.CancelledError:
                pass
        self._tasks = []
        if self._log is not None:
            self._log.close()
            self._log = None

    @property
    def state(self) -> str:
        if self.fault:
            return "FAULT"
        if self.held:
            return "HOLD"
        if self.waiting:
            return "WAIT"
        return "RUN" if self.queue else "IDLE"

    def free_slots(self) -> int:
        """Free queue slots as the robot reports them (ACK credits, STA queue_free)."""
        return self.slots - len(self.queue) - self.phantom

    @property
    def expected(self) -> int:
        return rlp.seq_add(self.last_rx, 1)

    # -- ByteSim ----------------------------------------------------------------------------------
    def attach(self, write: Callable[[bytes], None]) -> None:
        self._write = write
        self._splitter = rlp.LineSplitter()
        self._last_heard = time.monotonic()
        self._speak(1)  # a new connection: RLP/1 until its host asks for more

    def detach(self) -> None:
        self._write = None

    def write_raw(self, data: bytes) -> None:
        """Bytes onto the line as they are (a misbehaviour's frames: robot_lies.py), when a host is attached."""
        if self._write is not None:
            self._write(data)

    def feed(self, data: bytes) -> None:
        self._last_heard = time.monotonic()
        for line in self._splitter.feed(data):
            self._line(line)
        if self._ack_due:  # one cumulative ACK per received chunk keeps the return line free
            self._acknowledge()

    # -- receiving --------------------------------------------------------------------------------
    def _send(self, body: str) -> None:
        if self._write is not None:
            data = self.lies.outgoing(body) if self.lies else rlp.encode(body)
            if data:
                self._write(data)

    def _acknowledge(self) -> None:
        """ACK last_rx credits; RLP/2 with frames kept beyond a gap: SACK with their ranges."""
        self._ack_due = False
        free = self.free_slots()
        if self.ahead:  # bit i: frame last_rx + 2 + i (last_rx + 1 is the gap)
            mask = sum(1 << (rlp.seq_diff(s, self.last_rx) - 2) for s in self.ahead)
            self._send(rlp.sack(self.last_rx, free, mask))
        else:
            self._send(rlp.ack(self.last_rx, free))

    def _speak(self, version: int) -> None:
        self.proto = version
        if version < 2:
            self.ahead.clear()  # a host that speaks RLP/1 sends them again

    def _nak(self, reason: str) -> None:
        self.naks += 1
        self.discarding = True
        if self._ack_due:  # what was accepted before the bad frame is acknowledged first
            self._acknowledge()
        self._send(rlp.nak(self.expected, reason))

    def _line(self, line: bytes) -> None:
        self.frames_rx += 1
        try:
            body = rlp.decode(line)
            msg = rlp.parse_host(body)
        except rlp.FrameError as exc:
            if exc.reason == "CRC":
                self.crc_errors += 1
            else:
                self.syntax_errors += 1
            self._nak(exc.reason)
            return
        if isinstance(msg, str):
            if msg.startswith("PROTO"):
                self._negotiate(int(msg.split(" ")[1]))
            else:
                self._control(msg)
            return
        if self.proto >= 2:
            self._receive_selective(msg)
            return
        d = rlp.seq_diff(msg.seq, self.expected)
        if d == 0:
            if self.free_slots() <= 0:
                self._nak("FULL")
                return
            self.queue.append(msg)
            self.last_rx = msg.seq
            self.discarding = False
            self._ack_due = True
        elif d < 0:  # already received: acknowledge again, never execute twice
            self.duplicates += 1
            self._ack_due = True
        elif not self.discarding:
            self._nak("SEQ")
        # else: discarding until the expected seq arrives

    def _negotiate(self, version: int) -> None:
        """`!PROTO n`: answer `PROTO m` (m ≤ n); a robot that speaks only RLP/1 rejects it as any
        unknown control frame (NAK SYNTAX)."""
        if self.max_protocol < 2:
            self.syntax_errors += 1
            self._nak("SYNTAX")
            return
        self._speak(max(1, min(version, self.max_protocol)))
        self._send(rlp.proto(self.proto))

    def _receive_selective(self, msg: rlp.Move) -> None:
        """RLP/2: a frame at or beyond the expected one is kept (within the credits) and the queue
        takes the run that is complete; a duplicate is acknowledged again, never queued twice."""
        self._ack_due = True
        d = rlp.seq_diff(msg.seq, self.last_rx)
        if d <= 0 or msg.seq in self.ahead:
            self.duplicates += 1
            return
        if d > self.free_slots():
            self._nak("FULL")
            return
        self.ahead[msg.seq] = msg
        while self.expected in self.ahead:
            self.queue.append(self.ahead.pop(self.expected))
            self.last_rx = self.expected
        self.discarding = False

    def _control(self, verb: str) -> None:
        if verb == "HOLD":
            self.held, self.held_at = True, time.monotonic()
            self._stopped()
        elif verb == "GO":
            self.held = self.silence_held = False
            if self.waiting and self.queue and self.queue[0].verb == "WAIT" and not self.fault:
                self.waiting = False
                self._finish(self.queue[0], self.clock.now())
        elif verb == "ABORT":
            self.queue.clear()
            self.phantom = self.phantom_on_abort
            self.ahead.clear()
            self.held = self.silence_held = self.waiting = False
            self._stopped()
        elif verb == "RESET":
            self.queue.clear()
            self.phantom = 0
            self.ahead.clear()
            self.held = self.silence_held = self.waiting = self.fault = False
            self.discarding = False
            self.last_rx = self.last_exec = 0
            self._stopped()
        self.send_status()

    def flush_exe(self) -> None:
        """Send the EXE due (one cumulative EXE per executor tick)."""
        if self._exe_due is not None:
            self._send(rlp.exe(self._exe_due))
            self._exe_due = None

    def send_status(self) -> None:
        self.flush_exe()
        self._send(rlp.sta(self.state, self.last_rx, self.last_exec, self.free_slots(), self.pos))

    # -- execution --------------------------------------------------------------------------------
    def _stopped(self) -> None:
        if self.world is not None:
            self.world.motion_stopped(DEVICE)

    def _finish(self, m: rlp.Move, t: float) -> None:
        self.queue.popleft()
        self.last_exec = m.seq
        self.executed_count += 1
        if self.executed is not None:
            self.executed.append(m.seq)
        if self._log is not None:
            row = {"seq": m.seq, "verb": m.verb, "target": [round(v, 3) for v in self.pos], "t": round(t, 4)}
            if m.axis is not None and tuple(m.axis) != (0.0, 0.0, 1.0):  # a tilted tool axis (5-axis)
                row["axis"] = [round(v, 5) for v in m.axis]
            self._log.write(json.dumps(row) + "\n")
            self._log_dirty = True
        self._exe_due = m.seq  # EXE is cumulative: one per executor tick keeps the return line free
        if not self.queue:
            self.underruns += 1

    def _outside(self, p: tuple[float, float, float]) -> bool:
        if self.workspace is None:
            return False
        lo, hi = self.workspace
        return any(v < a - 1e-9 or v > b + 1e-9 for v, a, b in zip(p, lo, hi))

    def advance(self, t: float, now: float, deadline: float | None = None) -> float:
        """Execute queued moves over simulated time [t, now]; stop between moves once the wall
        clock (`time.perf_counter()`) passes `deadline`. Returns the simulated time reached."""
        self._next_finish = None
        done_any = False
        while t < now and self.queue and not (self.held or self.fault or self.waiting):
            head = self.queue[0]
            if head.verb == "MOVJ" and head.seq != self._head_seen:   # a travel move comes up (freeze@travel)
                self._head_seen, self.travels = head.seq, self.travels + 1
            if self.lies and self.lies.active("freeze"):  # fault: accepts moves, executes none (RUN)
                return now
            if deadline is not None and done_any and time.perf_counter() > deadline:
                return t   # at least one move per tick: a thread switch must not starve it
            done_any = True
            step = self._step(self.queue[0], t, now)
            if step is None:
                break
            t = step
        return now

    def _step(self, m: rlp.Move, t: float, now: float) -> float | None:
        """Run the head move from simulated time t, up to now: the time it ended, or None when
        the executor stops here (a WAIT, a fault, a move still under way)."""
        if m.verb == "WAIT":
            self.waiting = True
            return None
        if m.verb == "MARK":
            self.flush_exe()
            self._send(f"MRK {m.mark}")
            self._finish(m, t)
            return t
        target, speed = m.target, m.speed
        assert target is not None and speed is not None  # MOVJ / MOVL: parse_host sets both
        if self._outside(target):
            self.fault = True
            self._stopped()
            self._send(f"ERR {ERR_WORKSPACE} target {' '.join(rlp.fmt_mm(v) for v in target)} outside workspace")
            return None
        p0 = self.pos
        delta = [b - a for a, b in zip(p0, target)]
        dist = sum(d * d for d in delta) ** 0.5
        v = speed / 60.0
        need = dist / v
        if t + need <= now:
            p1, t1, done = target, t + need, True
        else:
            f = (now - t) * v / dist
            p1, t1, done = (p0[0] + f * delta[0], p0[1] + f * delta[1], p0[2] + f * delta[2]), now, False
        if self.world is not None and dist > 0:
            self.world.torch_moved(DEVICE, m.seq, p0, p1, t, t1)
        self.pos = p1
        if not done:
            self._next_finish = now + dist * (1.0 - f) / v   # when this move's EXE is due
            return None
        self._stopped()
        self._finish(m, t1)
        return float(t1)

    def _runnable(self) -> bool:
        return bool(self.queue) and not (self.held or self.fault or self.waiting)

    async def _exec_loop(self) -> None:
        last = self.clock.now()
        was = behind = laying = False
        while True:
            # tick fast while moving, slowly while idle (a move noticed at a tick starts then);
            # while moving, wake when the head move ends: its EXE leaves on time, as a real
            # controller's does, not up to a tick late (the host measures travel speed from EXEs)
            pause = self.tick_s if was else self.IDLE_TICK_S
            if was and self._next_finish is not None:
                to_end = self.clock.wall(self._next_finish - self.clock.now())
                pause = max(self.MIN_TICK_S, min(pause, to_end))
            # on the simulators' loop (sims/loop.py) a timer fires within microseconds of its
            # time: the EXE leaves at the move's end (the host measures travel speed from EXEs)
            # behind: a short real sleep, not sleep(0): in one process with the controller (--sim)
            # a loop that only yields to itself keeps the interpreter lock from the controller
            await asyncio.sleep(self.MIN_TICK_S if behind else min(pause, self.LAY_REST_S) if laying else pause)
            now = self.clock.now()
            reached = now
            deadline = time.perf_counter() + self.WORK_BUDGET_S
            if was:
                reached = self.advance(last, now, deadline)
                self.flush_exe()
            # deferred beads in what is left of the budget, and never past the head move's end
            # (its EXE leaves on time); more on the next pass of the loop
            if self._next_finish is not None:
                deadline = min(deadline, time.perf_counter() + self.clock.wall(self._next_finish - self.clock.now()))
            laid = self.world.settle(deadline) if self.world is not None else True
            was = self._runnable()
            behind, laying = was and reached < now, not laid
            last = reached
            if self._log_dirty and self._log is not None:
                self._log.flush()
                self._log_dirty = False

    async def _link_loop(self) -> None:
        # link timing is wall time, never scaled
        next_hb = time.monotonic() + self.heartbeat_s
        while True:
            await asyncio.sleep(0.05)
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + self.heartbeat_s
                self.hb += 1
                self._send(f"HB {self.hb}")
            if now - self._last_heard > self.link_timeout_s:
                self._speak(1)  # the host is gone: the next one negotiates again
                if not self.held and self.queue:
                    self.held = self.silence_held = True  # silence over 3 s holds motion
                    self._stopped()


async def serve(ctx: SimContext) -> list[Served]:
    """Start the robot simulator on cell.yaml's robot URL (or port 0 / a pty), per ctx."""
    dev = ctx.cell.devices.robot
    lim = ctx.cell.limits
    spec = parse_fault_spec(ctx.faults)
    attach(ctx)   # the world's process physics: the robot's substrate is the plane z = 0 of its frame
    sim = RobotSim(clock=ctx.clock, world=ctx.world, queue_slots=dev.queue_slots,
                   log_path=(Path(ctx.log_dir) / "robot.jsonl") if ctx.log_dir else None,
                   heartbeat_s=dev.heartbeat_s, link_timeout_s=dev.link_timeout_s,
                   workspace=(lim.workspace_min_mm, lim.workspace_max_mm),
                   faults=spec, fault_log=(Path(ctx.log_dir) / "faults.jsonl") if ctx.log_dir else None,
                   line_rate=dev.baud / 10.0)
    return await serve_serial(sim, DEVICE, dev, ctx, spec, {"protocol": "RLP/2 (RLP/1 on request)"})

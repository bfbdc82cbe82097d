"""Interlocks (docs/contract.md §5-6): act within one cycle, then record, then latch.

Sources: the cell I/O's input-change callback (door opened, E-stop pressed), the power
source's status every 10 ms cycle (arc lost for longer than the limit, wire stick, gas fault,
collision, error number) and its link error (missed watchdog / lost link), and the motion
link's link-lost event. On a trip, in this order and without awaiting anything:

1. drop weld start (and every other start bit): the next power-source cycle carries it;
2. hold motion (`!HOLD` written to the robot link at once / grbl feed hold `!`);
3. latch Fault or EStop in the state machine and stop the build task.

Then, asynchronously: read the position where motion stopped and journal the alarm with it.
Only an explicit reset clears the latch (and, for the E-stop, only once the input is released).
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from controller.runtime.build import BuildResult, BuildRunner
from controller.runtime.events import EventBus
from controller.journal.store import Journal
from controller.runtime.machine import CellMachine
from controller.ports import CellIOPort, MotionExecutor, PowerSourcePort
from drivers.cellio import CellInputs
from drivers.power import PowerStatus


@dataclass
class TripRecord:
    kind: str                # fault | estop
    message: str
    t_detect: float          # time.monotonic() when the input/status was read
    t_acted: float           # time.monotonic() when start was dropped and the hold written
    layer: int | None = None
    pass_: int | None = None
    position: tuple[float, float, float] | None = None
    power_cycle_at_trip: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)


class Interlocks:
    """Watches the devices and trips the cell. One instance per connected cell."""

    def __init__(self, *, machine: CellMachine, journal: Journal | None, bus: EventBus, power: PowerSourcePort,
                 executor: MotionExecutor, cellio: CellIOPort | None = None) -> None:
        self.m, self.journal, self.bus = machine, journal, bus
        self.power, self.ex, self.cellio = power, executor, cellio
        self.runner: BuildRunner | None = None  # the BuildRunner to stop, set while a build runs
        self.build_task: asyncio.Task[BuildResult] | None = None
        self.trips: list[TripRecord] = []
        self.on_trip: list[Callable[[TripRecord], None]] = []
        self._unsub: list[Callable[[], None]] = []
        self.pending: set[asyncio.Task[None]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None

    def arm(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._unsub.append(self.power.subscribe(self._on_power))
        self.power.on_error(lambda exc: self.fault(f"power source: {exc}"))
        if self.cellio is not None:
            self.cellio.on_change(self._on_inputs)
            self.cellio.on_error(lambda exc: self.fault(f"cell I/O: {exc}"))
        self.ex.on_link_lost(lambda exc: self.fault(f"link lost: {exc}"))

    def disarm(self) -> None:
        for u in self._unsub:
            try:
                u()
            except Exception:
                pass
        self._unsub.clear()

    # -- sources ------------------------------------------------------------------------------
    def _on_inputs(self, _prev: CellInputs, new: CellInputs) -> None:
        """CellIO input-change callback `(previous, new)`, called in the cycle that read the change."""
        if not new.estop_released and self.m.can("estop"):
            self.trip("estop", "E-stop pressed", t_detect=new.t)
        elif not new.door_closed and self.m.state.running:
            self.trip("fault", "door opened during the build", t_detect=new.t)

    def _on_power(self, st: PowerStatus) -> None:
        """Power-source faults while welding come from the ArcHandshake's on_fault (wall-time
        supervision: arc lost > 200 ms, wire stick, gas, collision, watchdog); here only the
        faults it does not watch outside a weld: a torch collision or gas fault at any time
        during a build."""
        if not self.m.state.running:
            return
        if not st.collision_ok:
            self.trip("fault", "collision (torch crash sensor)", t_detect=st.t)
        elif st.gas_fault:
            self.trip("fault", "gas fault", t_detect=st.t)

    # -- the action -----------------------------------------------------------------------------
    def fault(self, message: str) -> None:
        """Trip to Fault (a device callback: returns nothing)."""
        self.trip("fault", message)

    def trip(self, kind: str, message: str, t_detect: float | None = None) -> TripRecord | None:
        """Drop start, hold motion, latch. Idempotent while latched."""
        t0 = time.monotonic() if t_detect is None else t_detect
        # 1 + 2: act before anything else
        try:
            self.power.drop_all()
        except Exception:
            pass
        try:
            self.ex.hold_now()
        except Exception:
            pass
        t_acted = time.monotonic()
        event = "estop" if kind == "estop" else "fault"
        if not self.m.can(event):
            return None  # already latched (or disconnected): the action above is all there is
        runner = self.runner
        item = runner.current if runner is not None and self.m.state.running else None
        st = self.power.status
        rec = TripRecord(kind=event, message=message, t_detect=t0, t_acted=t_acted,
                         layer=item.layer if item else None, pass_=item.pass_ if item else None,
                         power_cycle_at_trip=st.cycle if st is not None else None)
        self.m.send(event, cause=message)
        self.trips.append(rec)
        if runner is not None and item is not None:
            runner.interrupted(message)
        elif runner is not None:  # tripped before the first bead (readiness, prepare): no bead to close
            runner.tripped = message
        if self.build_task is not None and not self.build_task.done():
            self.build_task.cancel()
        if self._loop is not None:
            task = self._loop.create_task(self._record(rec))
            self.pending.add(task)
            task.add_done_callback(self.pending.discard)
        for fn in self.on_trip:
            fn(rec)
        return rec

    async def settle(self, timeout: float = 3.0) -> None:
        """Wait until every trip is journaled with its position."""
        if self.pending:
            await asyncio.wait(list(self.pending), timeout=timeout)

    async def _record(self, rec: TripRecord) -> None:
        try:
            pos = await asyncio.wait_for(self.ex.held_position(), 2.0)
        except Exception:
            pos = None
        rec.position = (float(pos[0]), float(pos[1]), float(pos[2])) if pos is not None else None
        if self.journal is not None:
            self.journal.event("alarm", rec.message, state=rec.kind, layer=rec.layer, pass_=rec.pass_, pos=pos)
            stop = self.ex.stop_result  # the CNC's verified safe stop
            if stop is not None:
                self.journal.event("info", f"cnc safe stop: {stop.summary()}", layer=rec.layer, pass_=rec.pass_)
        self.bus.alarm(rec.kind, rec.message, layer=rec.layer, pass_=rec.pass_, position=rec.position)
        self.bus.update(state=self.m.state.value)

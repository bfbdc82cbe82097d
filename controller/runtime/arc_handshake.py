"""The arc handshake (docs/contract.md §5) as a small state machine on top of `PowerSource`.

    idle -> ready -> preflow -> ignition -> welding -> crater -> postflow -> idle
                                    \\-(1.5 s, retries)-/          any active state -> fault

Usage (the controller's build loop):

    arc = ArcHandshake(power, on_fault=hold_motion, on_transition=journal.record)
    await arc.start()      # returns at motion release (arc stable held 16 ms): send `!GO`
    ...                    # deposit; a fault while welding calls on_fault(exc) and sets
                           # arc.faulted; the weld start is already dropped
    await arc.stop()       # crater / burn-back (hold motion until arc stable falls), post-flow
    await arc.reset()      # error reset (rising edge) on the device, clear the latched fault

`start()` raises an `ArcFault` subclass naming the fault (IgnitionFailed after the retries,
GasFault, WireOut, WireStick, Collision, WatchdogMissed, ArcLost, LinkLost, FaultLatched when
a previous fault was not reset). Faults while active: arc stable lost for more than 200 ms,
wire stick, gas fault, wire out, collision, 3 cycles without the watchdog echo, a lost link:
the handshake drops weld start (and gas test / inch / retract) in the same cycle, latches the
fault and calls `on_fault`; only `reset()` clears it.

Timing: every timer here is supervision on the 10 ms bus (ignition timeout, 16 ms hold,
200 ms arc loss, watchdog): wall time, never divided by the time scale. The simulator's
process phases are scaled but never shorter than 2 cycles, so they always fit in these.
Every transition is recorded with its monotonic and Unix time for the journal.
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Callable

from drivers.errors import DeviceError, LinkLost
from controller.ports import CellIOPort, PowerSourcePort
from drivers.cellio import CellInputs
from drivers.power import PowerStatus
from core.errors import CellError

STATES = ("idle", "ready", "preflow", "ignition", "welding", "crater", "postflow", "fault")
ACTIVE = ("preflow", "ignition", "welding", "crater", "postflow")


class ArcFault(DeviceError):
    """A fault of the arc process; `fault` is its short name (journal, alarms)."""

    fault = "arc_fault"


class IgnitionFailed(ArcFault):
    fault = "ignition_failed"


class ArcLost(ArcFault):
    fault = "arc_loss"


class WireStick(ArcFault):
    fault = "wire_stick"


class GasFault(ArcFault):
    fault = "gas_fault"


class WireOut(ArcFault):
    fault = "wire_out"


class Collision(ArcFault):
    fault = "collision"


class WatchdogMissed(ArcFault):
    fault = "watchdog"


class PowerLinkLost(ArcFault):
    fault = "link_lost"


class FaultLatched(ArcFault):
    fault = "fault_latched"


class NotReady(ArcFault):
    fault = "not_ready"


@dataclass(frozen=True)
class Transition:
    """One state change: monotonic time (s), Unix time (s), from, to, why."""

    t: float
    unix: float
    frm: str
    to: str
    reason: str = ""

    def as_dict(self) -> dict[str, float | str]:
        return {"t": self.t, "unix": self.unix, "from": self.frm, "to": self.to, "reason": self.reason}


class ArcHandshake:
    """Ignition, welding and arc end against a `PowerSource`, with latched faults."""

    def __init__(self, power: PowerSourcePort, *, ignition_timeout_s: float = 1.5, ignition_retries: int = 2,
                 arc_hold_s: float = 0.016, arc_loss_s: float = 0.200, watchdog_cycles: int = 3,
                 ready_timeout_s: float = 1.0, end_timeout_s: float = 10.0,
                 on_transition: Callable[[Transition], None] | None = None,
                 on_fault: Callable[[ArcFault], None] | None = None) -> None:
        self.power = power
        self.ignition_timeout_s = ignition_timeout_s
        self.ignition_retries = ignition_retries
        self.arc_hold_s = arc_hold_s
        self.arc_loss_s = arc_loss_s
        self.watchdog_cycles = watchdog_cycles
        self.ready_timeout_s = ready_timeout_s
        self.end_timeout_s = end_timeout_s
        self.state = "idle"
        self.transitions: list[Transition] = []
        self.fault: ArcFault | None = None
        self.faulted = asyncio.Event()
        self.attempts = 0                     # ignition attempts of the last start()
        self._on_transition = on_transition
        self._on_fault = on_fault
        self._arc_false_since: float | None = None
        self._arc_true_since: float | None = None
        self._wd_miss = 0
        self._unsub = power.subscribe(self._on_status)
        power.on_error(self._on_power_error)

    def close(self) -> None:
        """Stop watching the power source's cycle."""
        self._unsub()

    # -- transitions and faults -------------------------------------------------------------
    def _go(self, to: str, reason: str = "") -> None:
        if to == self.state:
            return
        tr = Transition(time.monotonic(), time.time(), self.state, to, reason)
        self.transitions.append(tr)
        self.state = to
        if self._on_transition is not None:
            try:
                self._on_transition(tr)
            except Exception:  # the journal's trouble must not stop the interlock
                pass

    def _latch(self, exc: ArcFault) -> None:
        self.power.drop_all()                      # the next cycle carries it (<= 1 cycle)
        if self.fault is not None:
            return
        self.fault = exc
        self._go("fault", f"{exc.fault}: {exc}")
        self.faulted.set()
        if self._on_fault is not None:
            try:
                self._on_fault(exc)
            except Exception:
                pass

    def _where(self) -> str:
        return self.power.where()

    def _on_power_error(self, exc: CellError) -> None:
        if self.state in ACTIVE or self.state == "ready":
            self._latch(PowerLinkLost(f"{exc}"))

    def _on_status(self, st: PowerStatus) -> None:
        """Every cycle: watch the device while the process is active."""
        if st.arc_stable:
            self._arc_false_since = None
            if self._arc_true_since is None:
                self._arc_true_since = st.t
        else:
            self._arc_true_since = None
            if self._arc_false_since is None:
                self._arc_false_since = st.t
        self._wd_miss = 0 if st.watchdog_ok else self._wd_miss + 1
        if self.state not in ACTIVE or self.fault is not None:
            return
        w = self._where()
        if self._wd_miss >= self.watchdog_cycles:
            self._latch(WatchdogMissed(f"{w}: no watchdog echo for {self._wd_miss} cycles"))
        elif not st.collision_ok:
            self._latch(Collision(f"{w}: torch collision (collision OK fell); clear the torch, then reset"))
        elif st.gas_fault:
            self._latch(GasFault(f"{w}: gas fault (error {st.error_number}); check the gas supply, then reset"))
        elif st.wire_out:
            self._latch(WireOut(f"{w}: wire out (error {st.error_number}); load wire, then reset"))
        elif st.wire_stick:
            self._latch(WireStick(f"{w}: wire stuck in the pool (error {st.error_number}); cut the wire, then reset"))
        elif st.error_number == 50:
            self._latch(WatchdogMissed(f"{w}: the device dropped the start on its watchdog (error 50)"))
        elif st.error_number and self.state != "postflow":
            self._latch(ArcFault(f"{w}: device error {st.error_number}; see the source's manual, then reset"))
        elif self.state == "welding" and self._arc_false_since is not None \
                and st.t - self._arc_false_since >= self.arc_loss_s - 0.001:
            # measured from the first status without the arc: the loss began up to one cycle
            # earlier, so it has lasted at least arc_loss_s here (1 ms allowance for jitter)
            lost_ms = (st.t - self._arc_false_since) * 1000
            self._latch(ArcLost(f"{w}: arc lost for {lost_ms:.0f} ms (> {self.arc_loss_s * 1000:.0f} ms)"))

    # -- the handshake ------------------------------------------------------------------------
    async def _status(self) -> PowerStatus:
        try:
            st = await self.power.next_status()
        except LinkLost as exc:
            self._latch(PowerLinkLost(str(exc)))
            raise (self.fault or PowerLinkLost(str(exc))) from None  # the latched fault (the first one)
        if self.fault is not None:
            raise self.fault
        return st

    async def start(self) -> None:
        """Ignite: returns at motion release (arc stable held 16 ms); ArcFault otherwise."""
        if self.fault is not None:
            raise FaultLatched(f"{self._where()}: fault latched ({self.fault.fault}); reset first")
        if self.state == "welding":
            return
        self.faulted.clear()
        self.power.set_robot_ready(True)
        t0 = time.monotonic()
        while True:
            st = await self._status()
            if st.ready:
                break
            if time.monotonic() - t0 > self.ready_timeout_s:
                raise NotReady(f"{self._where()}: not ready after {self.ready_timeout_s:g} s "
                               f"(error {st.error_number}); check the source, then reset")
        self._go("ready", "power source ready")
        self.attempts = 0
        last = "no current flow"
        while self.attempts <= self.ignition_retries:
            self.attempts += 1
            self.power.set_weld_start(True)
            self._go("preflow", f"weld start (attempt {self.attempts})")
            t_start = time.monotonic()
            while time.monotonic() - t_start <= self.ignition_timeout_s:
                st = await self._status()
                if self.state == "preflow" and st.current_flow:
                    self._go("ignition", "current flow")
                if st.arc_stable and self._arc_true_since is not None \
                        and st.t - self._arc_true_since >= self.arc_hold_s:
                    if self.state == "preflow":
                        self._go("ignition", "current flow")
                    self._arc_false_since = None
                    self._go("welding", f"arc stable held {self.arc_hold_s * 1000:.0f} ms: motion release")
                    return
                last = "no current flow" if not st.current_flow else "arc not stable"
            # ignition timeout: drop the start, let the source settle two cycles, retry
            self.power.set_weld_start(False)
            self._go("ready", f"ignition timeout {self.ignition_timeout_s:g} s ({last})")
            for _ in range(2):
                await self._status()
        exc = IgnitionFailed(f"{self._where()}: no stable arc after {self.attempts} attempts of "
                             f"{self.ignition_timeout_s:g} s ({last}); check wire, gas and contact tip")
        self._latch(exc)
        raise exc

    async def stop(self) -> None:
        """Arc end: drop weld start, wait for arc stable to fall (crater, burn-back) and for
        process active to fall (post-flow). Motion stays held until this returns."""
        if self.fault is not None:
            self.power.drop_all()
            raise self.fault
        if self.state == "idle":
            return
        self.power.set_weld_start(False)
        self._go("crater", "weld start dropped")
        t0 = time.monotonic()
        while True:
            st = await self._status()
            if self.state == "crater" and not st.arc_stable:
                self._go("postflow", "arc stable fell (burn-back done)")
            if self.state == "postflow" and not st.process_active:
                break
            if time.monotonic() - t0 > self.end_timeout_s:
                exc = ArcFault(f"{self._where()}: arc end not finished after {self.end_timeout_s:g} s")
                self._latch(exc)
                raise exc
        # a wire stuck at the arc end shows once the burn-back is over
        st = await self._status()
        self._go("idle", "post-flow done")

    async def reset(self) -> None:
        """Error reset on the device (rising edge), clear the latched fault, back to idle."""
        self.power.drop_all()
        await self.power.error_reset()
        self.fault = None
        self.faulted.clear()
        self._wd_miss = 0
        self._go("idle", "error reset")


def drop_start_on_unsafe(io: CellIOPort, power: PowerSourcePort,
                         on_trip: Callable[[CellInputs], None] | None = None) -> None:
    """Wire the cell I/O interlock: when a safety input goes bad (door open, E-stop, gas
    pressure, fume extraction), drop every start bit in the cycle the input is read; the next
    power-source cycle carries it. `io` is a `drivers.cellio.CellIO` (anything with
    `on_change(fn(prev, new))` whose readings have `safe_to_weld()`)."""
    def _check(prev: CellInputs, new: CellInputs) -> None:
        if not new.safe_to_weld():
            power.drop_all()
            if on_trip is not None:
                on_trip(new)
    io.on_change(_check)

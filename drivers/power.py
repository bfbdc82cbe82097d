"""The synergic power source: one interface (`PowerSource`), two transports (Modbus, CAN).

Usage (the controller):

    ps = open_power_source(cell.devices.power_source, material)   # drivers/registry.py
    await ps.connect()                 # first cycle sends every start bit cleared
    ps.set_job(mode=0, job=5); ps.set_wire_feed(6.2); ps.set_trims(arc=0.0, dynamic=0.0)
    ps.subscribe(record)               # record(PowerStatus) once per 10 ms cycle
    ps.on_error(fault)                 # fault(LinkLost | DeviceError) when the cycle stops
    ps.set_weld_start(True)            # taken by the next cycle (<= 1 cycle)
    st = ps.status                     # latest PowerStatus snapshot
    await ps.error_reset()             # rising edge on the error-reset bit
    await ps.close()

The cyclic task runs on the asyncio loop every `cycle_ms` (10 ms, wall time, never scaled):
it increments the watchdog counter, sends the whole command and reads the whole status in one
exchange, and hands the status to the subscribers. A reply that does not come within
`lost_after_cycles` cycles without a valid reply stop the cycle, reported as `LinkLost` naming the device and URL: writes
are never retried (a retried weld start could come late), the device's own watchdog drops the
start 100 ms after the counter stops.

Commands are checked before anything is sent: wire feed in [0, WFSmax] of the material, arc
trim within ±10, dynamic trim within ±5, mode 0..2, job 0..255; out of range is a
`CommandRangeError` (a CellError).
"""
from __future__ import annotations

import asyncio
import time
from abc import abstractmethod
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Self

from drivers.cyclic import CycleStats, CyclicDevice
from drivers.errors import LinkLost
from wire.power_registers import ARC_TRIM_LIMIT, COMMAND_BITS, DYNAMIC_TRIM_LIMIT, MODES, STATUS_BITS
from core.config import PowerSourceDevice
from core.errors import CellError

from core.material import Material


class CommandRangeError(CellError):
    """A power-source command outside its range; nothing was sent."""


@dataclass(frozen=True)
class PowerCommand:
    """Everything the host sends each cycle (0xF001 bits, mode/job, WFS, trims)."""

    weld_start: bool = False
    robot_ready: bool = False
    error_reset: bool = False
    gas_test: bool = False
    wire_inch: bool = False
    wire_retract: bool = False
    mode: int = 0
    job: int = 0
    wfs_m_min: float = 0.0
    arc_trim: float = 0.0
    dynamic_trim: float = 0.0

    def bits(self) -> dict[str, bool]:
        return {name: getattr(self, name) for name in COMMAND_BITS}


@dataclass(frozen=True)
class PowerStatus:
    """One cycle's reply: the 0xF101 bits, error number and actual values, time-stamped."""

    t: float                    # time.monotonic() when the reply arrived (wall)
    cycle: int                  # cycle number since connect
    counter: int                # watchdog counter sent in this cycle
    watchdog_echo: int
    heartbeat: bool = False
    ready: bool = False
    arc_stable: bool = False
    current_flow: bool = False
    main_current: bool = False
    collision_ok: bool = True
    gas_fault: bool = False
    wire_out: bool = False
    process_active: bool = False
    motion_release: bool = False
    wire_stick: bool = False
    error_number: int = 0
    voltage_v: float = 0.0
    current_a: float = 0.0
    wfs_m_min: float = 0.0
    command: PowerCommand = field(default_factory=PowerCommand)

    @property
    def watchdog_ok(self) -> bool:
        """The device echoed this cycle's counter."""
        return self.watchdog_echo == self.counter

    @classmethod
    def from_values(cls, *, t: float, cycle: int, counter: int, echo: int, bits: dict[str, bool],
                    error: int, voltage: float, current: float, wfs: float,
                    command: PowerCommand) -> "PowerStatus":
        return cls(t=t, cycle=cycle, counter=counter, watchdog_echo=echo,
                   **{k: bool(bits.get(k, False)) for k in STATUS_BITS},
                   error_number=int(error), voltage_v=voltage, current_a=current,
                   wfs_m_min=wfs, command=command)


class PowerSource(CyclicDevice[PowerStatus]):
    """A synergic MIG/MAG power source driven cyclically (docs/contract.md §5)."""

    device = "power_source"
    COUNTER_MOD = 0x10000       # watchdog counter width (u16 on Modbus, u8 on CAN)

    def __init__(self, url: str, material: "Material | None" = None, *, cycle_ms: float = 10.0,
                 timeout_ms: float | None = None, lost_after_cycles: int = 3) -> None:
        super().__init__(url, cycle_ms=cycle_ms, timeout_ms=timeout_ms, lost_after_cycles=lost_after_cycles)
        self.material = material
        self._cmd = PowerCommand()
        self._status: PowerStatus | None = None
        self._counter = 0
        self._cycle = 0

    @classmethod
    @abstractmethod
    def from_config(cls, cfg: PowerSourceDevice, material: Material | None = None, *,
                    config_dir: str | Path | None = None, url: str | None = None) -> Self:
        """The driver for `devices.power_source` of cell.yaml (drivers/registry.py picks the class)."""

    # -- transport hooks --------------------------------------------------------------------
    @abstractmethod
    async def _open(self) -> None:
        """Open the transport; raise LinkLost naming the URL if it cannot."""

    @abstractmethod
    async def _close(self) -> None:
        """Close the transport."""

    @abstractmethod
    async def _exchange(self, cmd: PowerCommand, counter: int) -> dict[str, Any]:
        """One cycle on the wire: send `cmd` with `counter`, return the decoded reply.

        The reply dict has keys echo, bits (by STATUS_BITS name), error, voltage, current, wfs.
        Raise LinkLost (no reply) or DeviceError (refused) — never retry.
        """

    def where(self) -> str:
        return f"power source at {self.url}"

    # -- lifecycle --------------------------------------------------------------------------
    async def connect(self) -> None:
        """Open the link, send one cycle with every start bit cleared, start the 10 ms cycle."""
        if self._task is not None:
            return
        self._closing = False
        self._error = None
        self._cmd = replace(PowerCommand(), mode=self._cmd.mode, job=self._cmd.job,
                            wfs_m_min=self._cmd.wfs_m_min, arc_trim=self._cmd.arc_trim,
                            dynamic_trim=self._cmd.dynamic_trim)
        await self._close()          # a reconnect after a lost link starts from a fresh transport
        await self._open()
        try:
            await self._one_cycle()      # errors here surface from connect() itself
        except BaseException:
            await self._close()
            raise
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"power cycle {self.url}")

    async def close(self) -> None:
        """Clear the start bits on the wire (best effort), stop the cycle, close the link."""
        if await self._stop_cycle() and self._error is None:
            self._cmd = replace(self._cmd, weld_start=False, gas_test=False, wire_inch=False,
                                wire_retract=False, error_reset=False)
            try:
                await self._one_cycle()
            except Exception:
                pass
        await self._close()
        self._fail_waiters(LinkLost(f"{self.where()}: link closed"))

    @property
    def connected(self) -> bool:
        return self._task is not None and self._error is None

    # -- commands (checked before anything is sent; taken by the next cycle) -----------------
    @property
    def command(self) -> PowerCommand:
        return self._cmd

    def set_job(self, mode: int = 0, job: int = 0) -> None:
        """Select the synergic mode (0 MIG, 1 pulse, 2 CMT-like) and job number (0..255)."""
        if mode not in MODES:
            raise CommandRangeError(f"{self.where()}: mode {mode} unknown; use 0 (synergic MIG), 1 (pulse) or 2 (CMT-like)")
        if not 0 <= int(job) <= 255 or int(job) != job:
            raise CommandRangeError(f"{self.where()}: job number {job} outside 0..255")
        self._cmd = replace(self._cmd, mode=int(mode), job=int(job))

    def set_wire_feed(self, wfs_m_min: float) -> None:
        """Wire feed speed command in m/min, within [0, WFSmax] of the material."""
        wmax = self.material.ribeiro.wfs_max_m_min if self.material is not None else 327.67
        if not 0.0 <= wfs_m_min <= wmax + 1e-9:
            name = f" of {self.material.name}" if self.material is not None else ""
            raise CommandRangeError(
                f"{self.where()}: wire feed {wfs_m_min:g} m/min outside 0..{wmax:g} m/min (WFSmax{name}); "
                "nothing was sent")
        self._cmd = replace(self._cmd, wfs_m_min=float(wfs_m_min))

    def set_trims(self, arc: float = 0.0, dynamic: float = 0.0) -> None:
        """Arc-length trim (±10) and dynamic trim (±5), 0.1 steps."""
        if not -ARC_TRIM_LIMIT <= arc <= ARC_TRIM_LIMIT:
            raise CommandRangeError(f"{self.where()}: arc-length trim {arc:g} outside ±{ARC_TRIM_LIMIT:g}; nothing was sent")
        if not -DYNAMIC_TRIM_LIMIT <= dynamic <= DYNAMIC_TRIM_LIMIT:
            raise CommandRangeError(f"{self.where()}: dynamic trim {dynamic:g} outside ±{DYNAMIC_TRIM_LIMIT:g}; nothing was sent")
        self._cmd = replace(self._cmd, arc_trim=float(arc), dynamic_trim=float(dynamic))

    def set_weld_start(self, on: bool) -> None:
        """Weld start bit. Dropping it is always accepted (even after a lost link); raising it
        on a stopped cycle raises the error that stopped it."""
        if on and self._error is not None:
            raise self._error
        self._cmd = replace(self._cmd, weld_start=bool(on))

    def set_robot_ready(self, on: bool) -> None:
        self._cmd = replace(self._cmd, robot_ready=bool(on))

    def set_gas_test(self, on: bool) -> None:
        self._cmd = replace(self._cmd, gas_test=bool(on))

    def set_wire_inch(self, on: bool) -> None:
        self._cmd = replace(self._cmd, wire_inch=bool(on), wire_retract=False if on else self._cmd.wire_retract)

    def set_wire_retract(self, on: bool) -> None:
        self._cmd = replace(self._cmd, wire_retract=bool(on), wire_inch=False if on else self._cmd.wire_inch)

    def drop_all(self) -> None:
        """Clear every start bit (weld start, gas test, inch, retract): the interlock action. The
        cleared bits go out at once, not at the next cycle."""
        self._cmd = replace(self._cmd, weld_start=False, gas_test=False, wire_inch=False, wire_retract=False)
        self.cycle_now()

    async def error_reset(self) -> PowerStatus:
        """Give a rising edge on the error-reset bit (held 2 cycles, then cleared); latest status."""
        self._cmd = replace(self._cmd, error_reset=False)
        await self.next_status()
        self._cmd = replace(self._cmd, error_reset=True)
        await self.next_status()
        await self.next_status()
        self._cmd = replace(self._cmd, error_reset=False)
        return await self.next_status()

    # -- status -----------------------------------------------------------------------------
    @property
    def status(self) -> PowerStatus | None:
        """The latest status snapshot (None before connect)."""
        return self._status

    async def next_status(self) -> PowerStatus:
        """Wait for the next cycle's status; LinkLost / DeviceError if the cycle has stopped."""
        return await self._next_cycle()

    # -- the cycle --------------------------------------------------------------------------
    async def _one_cycle(self) -> PowerStatus:
        self._counter = (self._counter + 1) % self.COUNTER_MOD
        cmd, counter = self._cmd, self._counter
        try:
            rep = await self.reply_within(self._exchange(cmd, counter))
        except asyncio.TimeoutError:
            raise LinkLost(f"{self.where()}: no reply within {self.timeout_s * 1000:g} ms "
                           f"(cycle {self._cycle}); check the device is on and the URL/cable") from None
        except (ConnectionError, OSError) as exc:
            raise LinkLost(f"{self.where()}: link dropped ({exc}); check the device and the URL") from None
        st = PowerStatus.from_values(t=time.monotonic(), cycle=self._cycle, counter=counter,
                                     echo=rep["echo"], bits=rep["bits"], error=rep["error"],
                                     voltage=rep["voltage"], current=rep["current"], wfs=rep["wfs"],
                                     command=cmd)
        self._cycle += 1
        self._status = st
        return st


__all__ = ["PowerSource", "PowerCommand", "PowerStatus", "CommandRangeError", "CycleStats"]

"""Cell I/O over Modbus TCP: door, E-stop, gas, fume extraction, beacon, door lock, pyrometer.

The remote I/O coupler of docs/contract.md §5 (device id 1): discrete inputs 0 door closed, 1 E-stop
released, 2 gas pressure OK, 3 fume extraction running; coils 0 gas valve, 1-3 beacon green /
amber / red, 4 door lock; input registers 0 part temperature (0.1 °C), 1 gas flow (0.1 L/min).

Usage (the controller):

    io = CellIO(cell.devices.cellio.url)
    io.on_change(interlock)      # interlock(prev, new) in the cycle the input is read:
                                 # e.g. drop the power source's weld start at once
    await io.connect()
    io.inputs.door_closed, io.inputs.estop_released, io.inputs.gas_ok, io.inputs.fume_ok
    io.part_temperature_c, io.gas_flow_l_min
    io.set_gas_valve(True); io.set_beacon("amber"); io.set_door_lock(True)

Every `cycle_ms` (10 ms, wall time) the driver reads the inputs first (and calls the change
callbacks at once), then the two input registers, and writes the coils when they changed.
No valid reply for `lost_after_cycles` cycles stops the cycle with LinkLost naming the URL; all inputs are
then treated as unsafe by `inputs_safe()`.
"""
from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, fields, replace
from typing import Any, Awaitable, Callable, Sequence

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from drivers.cyclic import CyclicDevice
from drivers.errors import DeviceError, LinkLost
from wire.cellio_map import COILS, INPUT_REGISTERS, INPUTS, from_register
from wire.urls import parse_tcp_url
from core.errors import CellError

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)



@dataclass(frozen=True)
class CellInputs:
    """One cycle's reading of the coupler."""

    t: float                      # time.monotonic() of the discrete-input reply
    door_closed: bool = False
    estop_released: bool = False
    gas_ok: bool = False
    fume_ok: bool = False
    part_temperature_c: float = float("nan")
    gas_flow_l_min: float = 0.0

    def safe_to_weld(self) -> bool:
        """Door closed, E-stop released, gas pressure and fume extraction OK."""
        return self.door_closed and self.estop_released and self.gas_ok and self.fume_ok

    def switches(self) -> tuple[bool, ...]:
        """The discrete inputs, in the order of SWITCHES (a change of any is an input change)."""
        return tuple(bool(getattr(self, n)) for n in SWITCHES)


# the discrete inputs CellInputs holds: each read from the coupler by its name in the signal map
SWITCHES: tuple[str, ...] = tuple(f.name for f in fields(CellInputs) if f.type in (bool, "bool"))


def decode_inputs(bits: Sequence[bool], t: float, prev: CellInputs, names: Sequence[str] = INPUTS) -> CellInputs:
    """The coupler's discrete inputs as CellInputs, each by its name: `names[i]` (the signal map,
    wire/cellio_map.INPUTS) is the name of input `i`, so a reordered map never swaps the door and
    the E-stop. The registers are kept from `prev` (read later in the cycle)."""
    if len(bits) < len(names):
        raise DeviceError(f"cell I/O: {len(bits)} discrete inputs read, the signal map names {len(names)}")
    by_name = dict(zip(names, (bool(b) for b in bits)))
    missing = [n for n in SWITCHES if n not in by_name]
    if missing:
        raise DeviceError(f"cell I/O: the signal map has no input named {', '.join(missing)} "
                          "(wire/cellio_map.INPUTS against drivers/cellio.CellInputs)")
    return CellInputs(t, door_closed=by_name["door_closed"], estop_released=by_name["estop_released"],
                      gas_ok=by_name["gas_ok"], fume_ok=by_name["fume_ok"],
                      part_temperature_c=prev.part_temperature_c, gas_flow_l_min=prev.gas_flow_l_min)


class CellIO(CyclicDevice[CellInputs]):
    """Cyclic driver of the cell's I/O coupler."""

    device = "cellio"

    def __init__(self, url: str, *, device_id: int = 1, cycle_ms: float = 10.0, timeout_ms: float | None = None,
                 lost_after_cycles: int = 3) -> None:
        super().__init__(url, cycle_ms=cycle_ms, timeout_ms=timeout_ms, lost_after_cycles=lost_after_cycles)
        self.device_id = device_id
        self._client: AsyncModbusTcpClient | None = None
        self._inputs = CellInputs(t=0.0)
        self._coils = {k: False for k in COILS}
        self._written: dict[str, bool] | None = None
        self._change: list[Callable[[CellInputs, CellInputs], None]] = []
        self.cycles = 0

    def where(self) -> str:
        return f"cell I/O (Modbus TCP, device id {self.device_id}) at {self.url}"

    # -- lifecycle ---------------------------------------------------------------------------
    async def connect(self) -> None:
        """Connect, read once (errors surface here), start the cycle."""
        host, port = parse_tcp_url(self.url)
        client = AsyncModbusTcpClient(host, port=port, timeout=max(self.timeout_s, 1.0), retries=0,
                                      reconnect_delay=0)
        if not await client.connect():
            client.close()
            raise LinkLost(f"{self.where()}: cannot connect; is the coupler (or `cell sim up`) running?")
        client.ctx.comm_params.timeout_connect = max(self.timeout_s, 1.0)  # backs up reply_within()
        self._client = client
        self._error = None
        self._written = None
        self._closing = False
        try:
            await self._one_cycle()
        except BaseException:
            client.close()
            self._client = None
            raise
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"cellio {self.url}")

    async def close(self) -> None:
        await self._stop_cycle()
        if self._client is not None:
            self._client.close()
            self._client = None

    # -- inputs ------------------------------------------------------------------------------
    @property
    def inputs(self) -> CellInputs:
        """The latest reading (door_closed, estop_released, gas_ok, fume_ok, temperature, flow)."""
        return self._inputs

    @property
    def part_temperature_c(self) -> float:
        return self._inputs.part_temperature_c

    @property
    def gas_flow_l_min(self) -> float:
        return self._inputs.gas_flow_l_min

    def inputs_safe(self) -> bool:
        """Safe to weld: link up and every safety input good."""
        return self._error is None and self._task is not None and self._inputs.safe_to_weld()

    def on_change(self, fn: Callable[[CellInputs, CellInputs], None]) -> None:
        """Call `fn(previous, new)` in the cycle a discrete input changes (before the registers are read)."""
        self._change.append(fn)

    async def next_inputs(self) -> CellInputs:
        """Wait for the next cycle's reading; LinkLost if the cycle has stopped."""
        return await self._next_cycle()

    # -- outputs -----------------------------------------------------------------------------
    @property
    def coils(self) -> dict[str, bool]:
        return dict(self._coils)

    def set_gas_valve(self, on: bool) -> None:
        self._coils["gas_valve"] = bool(on)

    def set_beacon(self, color: str | None) -> None:
        """Light one beacon lamp: 'green', 'amber', 'red' or None (all off)."""
        if color not in (None, "green", "amber", "red"):
            raise CellError(f"{self.where()}: beacon colour {color!r} unknown; use green, amber or red")
        for c in ("green", "amber", "red"):
            self._coils[f"beacon_{c}"] = c == color

    def set_door_lock(self, on: bool) -> None:
        self._coils["door_lock"] = bool(on)

    # -- the cycle ---------------------------------------------------------------------------
    async def _call(self, coro: Awaitable[Any]) -> Any:
        try:
            rr = await self.reply_within(coro)
        except (asyncio.TimeoutError, ModbusException) as exc:
            raise LinkLost(f"{self.where()}: no reply within {self.timeout_s * 1000:g} ms ({str(exc) or 'timeout'}); "
                           "check the coupler and the URL") from None
        except (ConnectionError, OSError) as exc:
            raise LinkLost(f"{self.where()}: link dropped ({exc})") from None
        if rr.isError():
            raise DeviceError(f"{self.where()}: coupler refused the request (exception {getattr(rr, 'exception_code', '?')}); "
                              "check its I/O map against docs/contract.md §5")
        return rr

    async def _one_cycle(self) -> CellInputs:
        c, dev = self._client, self.device_id
        if c is None or not c.connected:
            raise LinkLost(f"{self.where()}: not connected")
        di = await self._call(c.read_discrete_inputs(0, count=len(INPUTS), device_id=dev))
        prev = self._inputs
        new = decode_inputs(di.bits, time.monotonic(), prev)
        if prev.switches() != new.switches() and self.cycles:
            self._inputs = new
            for fn in list(self._change):
                try:
                    fn(prev, new)
                except Exception:
                    pass
        ir = await self._call(c.read_input_registers(0, count=len(INPUT_REGISTERS), device_id=dev))
        regs = dict(zip(INPUT_REGISTERS, ir.registers))
        new = replace(new, part_temperature_c=from_register(regs["part_temperature_c"]),
                      gas_flow_l_min=from_register(regs["gas_flow_l_min"]))
        self._inputs = new
        if self._written != self._coils:
            want = dict(self._coils)
            await self._call(c.write_coils(0, [want[k] for k in COILS], device_id=dev))
            self._written = want
        self.cycles += 1
        return new

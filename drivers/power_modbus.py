"""Power source over Modbus TCP (`tcp://host:port`) or RTU (any pyserial URL), pymodbus 3.

One read/write-multiple-registers call (0x17) per cycle: write the command block
0xF000..0xF00D, read the status block 0xF100..0xF110 (docs/contract.md §5), device id 1 by default.
The pymodbus client runs with retries=0 and no automatic reconnect: a lost reply is a lost
link (LinkLost), never silently repeated.
"""
from __future__ import annotations


import logging
from pathlib import Path
from typing import Any, Self

from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerType

from core.config import PowerSourceDevice
from core.material import Material
from drivers.errors import DeviceError, LinkLost
from drivers.power import PowerCommand, PowerSource
from wire.urls import parse_tcp_url
from wire.power_registers import (
    COMMAND_BITS, POWER_MAP, STATUS_BITS, RegisterMap, decode_block, encode_command_block,
    pack_bits, unpack_bits,
)

# pymodbus logs every timeout at ERROR level; the driver reports it as LinkLost instead.
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

_EXC_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
             4: "device failure", 6: "device busy", 0x0B: "gateway target did not respond"}


class ModbusPowerSource(PowerSource):
    """`PowerSource` over Modbus TCP or RTU."""

    def __init__(self, url: str, material: Material | None = None, *, device_id: int = 1, cycle_ms: float = 10.0,
                 timeout_ms: float | None = None, rtu: bool | None = None, baudrate: int = 115200,
                 register_map: RegisterMap = POWER_MAP, lost_after_cycles: int = 3) -> None:
        super().__init__(url, material, cycle_ms=cycle_ms, timeout_ms=timeout_ms,
                         lost_after_cycles=lost_after_cycles)
        self.device_id = device_id
        self.rtu = (not url.startswith("tcp://")) if rtu is None else rtu
        self.baudrate = baudrate
        self.map = register_map.validate()
        self._client: AsyncModbusTcpClient | AsyncModbusSerialClient | None = None

    @classmethod
    def from_config(cls, cfg: PowerSourceDevice, material: Material | None = None, *,
                    config_dir: str | Path | None = None, url: str | None = None) -> Self:
        """`devices.power_source` with transport modbus_tcp or modbus_rtu (`config_dir` unused)."""
        return cls(url or cfg.url, material, device_id=cfg.device_id, cycle_ms=cfg.cycle_ms, timeout_ms=cfg.timeout_ms,
                   lost_after_cycles=cfg.lost_after_cycles, rtu=cfg.transport == "modbus_rtu")

    def where(self) -> str:
        kind = "Modbus RTU" if self.rtu else "Modbus TCP"
        return f"power source ({kind}, device id {self.device_id}) at {self.url}"

    async def _open(self) -> None:
        timeout = self.timeout_s
        client: AsyncModbusTcpClient | AsyncModbusSerialClient
        if self.rtu:
            if self.url.startswith("tcp://"):
                raise DeviceError(f"{self.where()}: Modbus RTU needs a serial URL (a port, socket://, a pty), not tcp://")
            client = AsyncModbusSerialClient(self.url, framer=FramerType.RTU, baudrate=self.baudrate,
                                             timeout=max(timeout, 1.0), retries=0, reconnect_delay=0)
        else:
            host, port = parse_tcp_url(self.url)
            client = AsyncModbusTcpClient(host, port=port, timeout=max(timeout, 1.0), retries=0,
                                          reconnect_delay=0)
        ok = await client.connect()
        if not ok:
            client.close()
            raise LinkLost(f"{self.where()}: cannot connect; is the device (or `cell sim up`) running?")
        # pymodbus's own per-request timeout only backs up reply_within() (which knows a late
        # timer from a silent device)
        client.ctx.comm_params.timeout_connect = max(timeout, 1.0)
        self._client = client

    async def _close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    async def _exchange(self, cmd: PowerCommand, counter: int) -> dict[str, Any]:
        client = self._client
        if client is None or not client.connected:
            raise LinkLost(f"{self.where()}: not connected")
        m = self.map
        words = encode_command_block({
            "watchdog": counter, "command_bits": pack_bits(cmd.bits(), COMMAND_BITS),
            "mode": cmd.mode, "job": cmd.job, "wfs_command": cmd.wfs_m_min,
            "arc_trim": cmd.arc_trim, "dynamic_trim": cmd.dynamic_trim}, m)
        try:
            rr = await client.readwrite_registers(
                read_address=m.status_start, read_count=m.status_count,
                write_address=m.command_start, values=words, device_id=self.device_id)
        except ModbusException as exc:
            raise LinkLost(f"{self.where()}: no reply within {self.timeout_s * 1000:g} ms ({exc})") from None
        if rr.isError():
            code = getattr(rr, "exception_code", 0)
            text = _EXC_TEXT.get(code, f"exception {code}")
            if code == 2:
                raise DeviceError(
                    f"{self.where()}: device rejected the register map ({text}) for command block "
                    f"0x{m.command_start:04X}..0x{m.command_start + m.command_count - 1:04X} / status block "
                    f"0x{m.status_start:04X}..0x{m.status_start + m.status_count - 1:04X}; "
                    "check the register map against the device's interface description")
            raise DeviceError(f"{self.where()}: device answered {text} to read/write registers")
        regs = list(rr.registers)
        if len(regs) < m.status_count:
            raise DeviceError(f"{self.where()}: short reply ({len(regs)} of {m.status_count} registers)")
        v = decode_block(regs, "status", m)
        return {"echo": int(v["watchdog_echo"]), "bits": unpack_bits(int(v["status_bits"]), STATUS_BITS),
                "error": int(v["error_number"]), "voltage": v["voltage"], "current": v["current"],
                "wfs": v["wfs_actual"]}

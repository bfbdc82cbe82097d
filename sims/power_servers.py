"""The power-source simulator's transports: Modbus TCP, Modbus RTU and a CAN node.

`serve_modbus_tcp` / `serve_modbus_rtu` put a `PowerSourceSim` behind the Modbus server of
sims/modbus_server.py through its register view (`PowerModbusView`); `CanNode` answers every WELD_CMD on a python-can bus with WELD_STATUS and
WELD_ACTUALS (config/power_source.dbc) and `serve_can` starts it. Each returns (url, close) and
starts the model's ticking. `sims.power_sim.serve(ctx)` picks the one cell.yaml names.
"""
from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, Protocol

from sims.power_params import HostCommand, PowerStatus
from wire.can_codec import DEFAULT_DBC, CanCodec
from wire.can_net import open_bus
from wire.power_registers import (
    COMMAND_BITS, POWER_MAP, STATUS_BITS, decode_block, pack_bits, to_raw, unpack_bits,
)

Close = Callable[[], Awaitable[None]]


class PowerSourceModel(Protocol):
    """What a transport needs of the power-source model (power_sim.py: PowerSourceSim)."""

    cmd: HostCommand          # the last host cycle's command

    def silent(self) -> bool: ...
    async def run(self) -> None: ...
    def status(self) -> PowerStatus: ...
    def command(self, bits: dict[str, bool], mode: int, job: int, wfs: float, arc_trim: float,
                dynamic_trim: float, counter: int) -> None: ...


# --- Modbus -----------------------------------------------------------------------------------

class PowerModbusView:
    """The source's Modbus holding registers (docs/contract.md §5, wire/power_registers.py) for the
    server of sims/modbus_server.py: a write of the command block is one host cycle."""

    def __init__(self, sim: PowerSourceModel) -> None:
        self.sim = sim

    def silent(self) -> bool:
        return self.sim.silent()

    async def run(self) -> None:
        await self.sim.run()

    def read(self, fc: int, address: int, count: int) -> list[int] | None:
        """Function codes 3 / 23: status or command holding registers."""
        m = POWER_MAP
        if fc not in (3, 23):
            return None
        if m.status_start <= address and address + count <= m.status_start + m.status_count:
            words = self._status_words()
            return words[address - m.status_start:address - m.status_start + count]
        if m.command_start <= address and address + count <= m.command_start + m.command_count:
            return self._command_words()[address - m.command_start:address - m.command_start + count]
        return None

    def write(self, fc: int, address: int, values: list[int]) -> bool:
        """Function codes 6 / 16 / 23 on the command registers: one host cycle's command."""
        m = POWER_MAP
        if fc not in (6, 16, 23):
            return False
        if not (m.command_start <= address and address + len(values) <= m.command_start + m.command_count):
            return False
        words = self._command_words()
        words[address - m.command_start:address - m.command_start + len(values)] = values
        v = decode_block(words, "command")
        self.sim.command(unpack_bits(int(v["command_bits"]), COMMAND_BITS), int(v["mode"]), int(v["job"]),
                         v["wfs_command"], v["arc_trim"], v["dynamic_trim"], int(v["watchdog"]))
        return True

    def _command_words(self) -> list[int]:
        c, m = self.sim.cmd, POWER_MAP
        words = [0] * m.command_count
        vals = {"watchdog": max(c.counter, 0), "command_bits": pack_bits(c.bits, COMMAND_BITS),
                "mode": c.mode, "job": c.job, "wfs_command": c.wfs, "arc_trim": c.arc_trim,
                "dynamic_trim": c.dynamic_trim}
        for r in m.registers:
            if r.direction == "command":
                words[r.address - m.command_start] = to_raw(vals[r.name], r)
        return words

    def _status_words(self) -> list[int]:
        s, m = self.sim.status(), POWER_MAP
        vals = {"watchdog_echo": s["echo"] & 0xFFFF, "status_bits": pack_bits(s["bits"], STATUS_BITS),
                "error_number": s["error"], "voltage": min(s["voltage"], 655.35),
                "current": min(s["current"], 6553.5), "wfs_actual": s["wfs"]}
        words = [0] * m.status_count
        for r in m.registers:
            if r.direction == "status":
                words[r.address - m.status_start] = to_raw(vals[r.name], r)
        return words


# --- CAN node ---------------------------------------------------------------------------------

class CanNode:
    """The power source as node `n` on a python-can bus: answers every WELD_CMD with
    WELD_STATUS and WELD_ACTUALS (config/power_source.dbc)."""

    def __init__(self, sim: PowerSourceModel, bus: Any, db: Any, node: int = 1) -> None:   # python-can / cantools: untyped
        self.sim = sim
        self.bus = bus
        self.codec = CanCodec(db, node)
        self._notifier: Any = None   # can.Notifier (python-can: untyped)

    def start(self) -> None:
        # lazy: python-can loads only when this path runs (start-up time)
        import can
        self._notifier = can.Notifier(self.bus, [self._on_message], loop=asyncio.get_running_loop())

    def _on_message(self, msg: Any) -> None:   # a can.Message
        if msg.arbitration_id != self.codec.cmd_id or msg.is_extended_id:
            return
        try:
            c = self.codec.decode_command(bytes(msg.data))
        except Exception:
            return  # a malformed frame is ignored, as a real node does
        self.sim.command(c["bits"], c["mode"], c["job"], c["wfs"], c["arc_trim"], c["dynamic_trim"],
                         c["counter"])
        if self.sim.silent():
            return
        for m in self.codec.encode_status(self.sim.status(), c["counter"]):
            try:
                self.bus.send(m)
            except Exception:
                pass

    def stop(self) -> None:
        if self._notifier is not None:
            self._notifier.stop(timeout=0.5)
            self._notifier = None
        self.bus.shutdown()


# --- serving ----------------------------------------------------------------------------------

async def serve_modbus_tcp(sim: PowerSourceModel, host: str = "127.0.0.1", port: int = 0,
                           device_id: int = 1) -> tuple[str, Close]:
    """Start the Modbus TCP server and the model's ticking; returns (url, close)."""
    # lazy: sims.up imports every simulator module (a cycle at import time)
    from sims.modbus_server import serve_tcp
    return await serve_tcp(PowerModbusView(sim), host, port, device_id)


async def serve_modbus_rtu(sim: PowerSourceModel, url: str = "socket://127.0.0.1:0",
                           device_id: int = 1) -> tuple[str, Close]:
    """Start the Modbus RTU server on a serial URL and the model's ticking; returns (url, close)."""
    # lazy: sims.up imports every simulator module (a cycle at import time)
    from sims.modbus_server import serve_rtu
    return await serve_rtu(PowerModbusView(sim), url, device_id)


async def serve_can(sim: PowerSourceModel, interface: str, channel: str, dbc: str | Path | None = None,
                    node: int = 1, allow_network: bool = False, **bus_kwargs: Any) -> tuple[str, Close]:
    """Start the CAN node on a python-can bus (kept on this host unless `allow_network`);
    returns (description, close)."""
    # lazy: cantools loads only when this path runs (start-up time)
    import cantools
    db = cantools.database.load_file(str(dbc or DEFAULT_DBC))
    bus = open_bus(interface, channel, allow_network=allow_network, device="power source simulator", **bus_kwargs)
    node_obj = CanNode(sim, bus, db, node)
    node_obj.start()
    ticker = asyncio.get_running_loop().create_task(sim.run())

    async def close() -> None:
        ticker.cancel()
        node_obj.stop()
    return f"can://{interface}/{channel}?node={node}", close

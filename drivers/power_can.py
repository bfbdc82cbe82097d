"""Power source over CAN: python-can for the bus, cantools for config/power_source.dbc.

Each 10 ms cycle the host sends `WELD_CMD` (0x200+n) with an incremented 8-bit alive counter
and waits for `WELD_STATUS` (0x180+n) and `WELD_ACTUALS` (0x280+n) echoing that counter. The
DBC describes node 1; node n shifts every id by n-1. No valid reply for `lost_after_cycles` cycles is a lost
link (LinkLost naming the interface and channel); a frame is never re-sent.

Buses: any python-can interface. `virtual` (in-process, tests), `udp_multicast` (between
processes on one host: `cell sim up` and the controller), `socketcan` on real hardware.
"""
from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any, Self

from core.config import PowerSourceDevice
from core.errors import ConfigError
from core.material import Material
from drivers.errors import DeviceError, LinkLost
from drivers.power import PowerCommand, PowerSource
from wire.can_codec import DEFAULT_DBC, CanCodec, dbc_path
from wire.can_net import check_channel, open_bus


class CanPowerSource(PowerSource):
    """`PowerSource` over CAN (python-can + cantools)."""

    COUNTER_MOD = 0x100

    def __init__(self, *, interface: str, channel: str, node: int = 1, dbc: str | Path = DEFAULT_DBC,
                 material: Material | None = None, cycle_ms: float = 10.0, timeout_ms: float | None = None,
                 allow_network: bool = False, lost_after_cycles: int = 3, **bus_kwargs: Any) -> None:
        super().__init__(f"can://{interface}/{channel}?node={node}", material, cycle_ms=cycle_ms,
                         timeout_ms=timeout_ms, lost_after_cycles=lost_after_cycles)
        # lazy: cantools loads only when this path runs (start-up time)
        import cantools
        try:
            db = cantools.database.load_file(str(dbc))
        except Exception as exc:
            raise ConfigError(f"{dbc}: cannot load the CAN database ({exc})") from None
        self.codec = CanCodec(db, node)
        self.interface, self.channel, self.node = interface, channel, node
        self.allow_network = allow_network

        check_channel(interface, channel, allow_network, self.where())  # refused before any I/O
        self.bus_kwargs = bus_kwargs
        self._bus: Any = None                # can.BusABC once open (python-can has no stubs here)
        self._notifier: Any = None
        self._pending: tuple[int, asyncio.Future[dict[str, Any]], dict[str, Any]] | None = None

    @classmethod
    def from_config(cls, cfg: PowerSourceDevice, material: Material | None = None, *,
                    config_dir: str | Path | None = None, url: str | None = None) -> Self:
        """`devices.power_source` with transport can; `url` overrides can.channel, `config_dir`
        resolves a relative can.dbc."""
        return cls(interface=cfg.can.interface, channel=url or cfg.can.channel, node=cfg.can.node,
                   dbc=dbc_path(cfg.can.dbc, config_dir), material=material, cycle_ms=cfg.cycle_ms,
                   timeout_ms=cfg.timeout_ms, allow_network=cfg.can.allow_network,
                   lost_after_cycles=cfg.lost_after_cycles)

    def where(self) -> str:
        return f"power source (CAN node {self.node}) on {self.interface} channel {self.channel}"

    async def _open(self) -> None:
        # lazy: python-can loads only when this path runs (start-up time)
        import can
        try:

            self._bus = open_bus(self.interface, self.channel, allow_network=self.allow_network,
                                 device=self.where(), **self.bus_kwargs)
        except ConfigError:
            raise
        except Exception as exc:
            raise LinkLost(f"{self.where()}: cannot open the bus ({exc})") from None
        self._notifier = can.Notifier(self._bus, [self._on_message], timeout=0.1,
                                      loop=asyncio.get_running_loop())

    async def _close(self) -> None:
        if self._notifier is not None:
            self._notifier.stop(timeout=0.5)
            self._notifier = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def _on_message(self, msg: Any) -> None:
        p = self._pending
        if p is None or msg.is_extended_id:
            return
        counter, fut, got = p
        try:
            if msg.arbitration_id == self.codec.sta_id:
                d = self.codec.decode_status(bytes(msg.data))
                if d["echo"] == counter:
                    got["status"] = d
            elif msg.arbitration_id == self.codec.act_id:
                d = self.codec.decode_actuals(bytes(msg.data))
                if d["echo"] == counter:
                    got["actuals"] = d
            else:
                return
        except Exception:
            return  # a malformed frame from another node is not ours to judge
        if "status" in got and "actuals" in got and not fut.done():
            fut.set_result(got)

    async def _exchange(self, cmd: PowerCommand, counter: int) -> dict[str, Any]:
        # lazy: python-can loads only when this path runs (start-up time)
        import can
        if self._bus is None:
            raise LinkLost(f"{self.where()}: not connected")
        fut = asyncio.get_running_loop().create_future()
        self._pending = (counter & 0xFF, fut, {})
        try:
            data = self.codec.encode_command(cmd, counter)
        except Exception as exc:
            raise DeviceError(f"{self.where()}: cannot encode WELD_CMD ({exc})") from None
        try:
            self._bus.send(can.Message(arbitration_id=self.codec.cmd_id, data=data, is_extended_id=False))
        except can.CanError as exc:
            raise LinkLost(f"{self.where()}: send failed ({exc})") from None
        try:
            got = await fut
        finally:
            self._pending = None
        st, act = got["status"], got["actuals"]
        return {"echo": st["echo"], "bits": st["bits"], "error": st["error"], "voltage": act["voltage"],
                "current": act["current"], "wfs": act["wfs"]}

"""Open the power-source driver that cell.yaml names (Modbus TCP/RTU or CAN).

Kept apart from drivers/power.py so the transports import the base class and the base class
never imports a transport (no import cycle).
"""
from __future__ import annotations

from pathlib import Path

from core.config import PowerSourceDevice
from core.material import Material
from drivers.errors import DeviceError
from drivers.power import PowerSource
from drivers.power_can import CanPowerSource
from drivers.power_modbus import ModbusPowerSource
from wire.can_codec import dbc_path


def open_power_source(cfg: PowerSourceDevice, material: Material | None = None,
                      config_dir: str | Path | None = None, url: str | None = None) -> PowerSource:
    """The driver for `devices.power_source` of cell.yaml (transport modbus_tcp|modbus_rtu|can)."""
    if cfg.transport in ("modbus_tcp", "modbus_rtu"):
        return ModbusPowerSource(url or cfg.url, material, device_id=cfg.device_id,
                                 cycle_ms=cfg.cycle_ms, timeout_ms=cfg.timeout_ms,
                                 lost_after_cycles=cfg.lost_after_cycles, rtu=cfg.transport == "modbus_rtu")
    if cfg.transport == "can":
        return CanPowerSource(interface=cfg.can.interface, channel=url or cfg.can.channel,
                              node=cfg.can.node, dbc=dbc_path(cfg.can.dbc, config_dir),
                              material=material, cycle_ms=cfg.cycle_ms, timeout_ms=cfg.timeout_ms,
                              allow_network=cfg.can.allow_network, lost_after_cycles=cfg.lost_after_cycles)
    raise DeviceError(f"power source: unknown transport '{cfg.transport}'")  # pragma: no cover

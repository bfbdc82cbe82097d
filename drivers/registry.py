"""Open a device from its cell.yaml section: one `open_*` per device kind, each looking the
section's protocol / transport up in a registry (as python-can's `BACKENDS` maps an interface
name to its bus class for `can.Bus(interface=...)`).

    ROBOT_BACKENDS   devices.robot.protocol          rlp1 -> drivers.robot.RobotLink
    CNC_BACKENDS     devices.cnc.protocol            grbl -> drivers.grbl.CncLink (imported on first use)
    POWER_BACKENDS   devices.power_source.transport  modbus_tcp, modbus_rtu -> ModbusPowerSource, can -> CanPowerSource
    CELLIO_BACKENDS  devices.cellio.transport        modbus_tcp -> drivers.cellio.CellIO

Each `open_*` builds the driver, it does not connect it: the caller awaits `connect()` (the
robot's with the journaled resume ticket) and closes it. A name missing from a registry is a
ConfigError naming the key and the known names; cell.yaml is checked against the same names
when it is loaded (core/config.py; tests/drivers/test_registry.py keeps both lists equal).

Adding a protocol: a driver class taking its kind's constructor arguments (those the open_*
below passes; a power source: `from_config`), one line in the registry, and its name in the
`...Name` Literal of core/config.py. A robot protocol reuses `drivers.liveness.LinkLiveness`
for its heard / late / lost accounting.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable, TypeVar

from core.config import CellIODevice, CncDevice, PowerSourceDevice, RobotDevice
from core.errors import ConfigError
from core.material import Material
from drivers.cellio import CellIO
from drivers.power import PowerSource
from drivers.power_can import CanPowerSource
from drivers.power_modbus import ModbusPowerSource
from drivers.robot import RobotLink

if TYPE_CHECKING:  # for the annotations only: at run time drivers.grbl loads in _grbl()
    from drivers.grbl import CncLink

E = TypeVar("E")


def _grbl() -> type[CncLink]:
    # Imported on first use, not with this module: drivers/grbl/ belongs to the grbl firmware
    # work (issue 15) and is edited apart from the registry, so a robot cell (and every robot,
    # power or cell I/O test) never loads the CNC driver, and the registry asks nothing of
    # grbl.py (no registration hook, no from_config): it maps the name to the class and calls
    # CncLink's own constructor.
    from drivers.grbl import CncLink

    return CncLink


ROBOT_BACKENDS: dict[str, type[RobotLink]] = {"rlp1": RobotLink}
CNC_BACKENDS: dict[str, Callable[[], type[CncLink]]] = {"grbl": _grbl}
POWER_BACKENDS: dict[str, type[PowerSource]] = {
    "modbus_tcp": ModbusPowerSource,
    "modbus_rtu": ModbusPowerSource,
    "can": CanPowerSource,
}
CELLIO_BACKENDS: dict[str, type[CellIO]] = {"modbus_tcp": CellIO}


def _backend(table: dict[str, E], name: str, key: str, what: str) -> E:
    """table[name], or a ConfigError naming cell.yaml's key and the known names."""
    try:
        return table[name]
    except KeyError:
        raise ConfigError(f"cell.yaml: key '{key}': unknown {what} {name!r}; known: {', '.join(table)}") from None


def open_robot(cfg: RobotDevice, *, time_scale: float = 1.0, url: str | None = None) -> RobotLink:
    """The robot link of `devices.robot` (by its `protocol`), not yet connected.

    `time_scale`: cell.time_scale; a simulated line carries that many times the bytes per wall
    second, so the link paces its writes to it (1 on hardware). `url` overrides cfg.url.
    """
    cls = _backend(ROBOT_BACKENDS, cfg.protocol, "devices.robot.protocol", "robot protocol")
    return cls(url or cfg.url, baud=cfg.baud, link_timeout_s=cfg.link_timeout_s, line_scale=time_scale)


def open_cnc(cfg: CncDevice, *, time_scale: float = 1.0, url: str | None = None) -> CncLink:
    """The CNC link of `devices.cnc` (by its `protocol`), not yet connected; `url` overrides cfg.url.

    `time_scale`: cell.time_scale; the link paces its writes to the simulated line's rate, as the
    robot link does (1 on hardware).
    """
    cls = _backend(CNC_BACKENDS, cfg.protocol, "devices.cnc.protocol", "CNC protocol")()
    return cls(url or cfg.url, baud=cfg.baud, rx_buffer_bytes=cfg.rx_buffer_bytes, status_hz=cfg.status_hz,
               homing_timeout_s=cfg.homing_timeout_s, line_scale=time_scale)


def open_power_source(cfg: PowerSourceDevice, material: Material | None = None,
                      config_dir: str | Path | None = None, url: str | None = None, *,
                      timeout_ms: float | None = None) -> PowerSource:
    """The power source of `devices.power_source` (by its `transport`), not yet connected.

    `config_dir` resolves a relative `can.dbc`; `url` overrides cfg.url (CAN: the channel);
    `timeout_ms` overrides cfg.timeout_ms (in-process simulators share the controller's GIL).
    """
    cls = _backend(POWER_BACKENDS, cfg.transport, "devices.power_source.transport", "power-source transport")
    if timeout_ms is not None:
        cfg = cfg.model_copy(update={"timeout_ms": timeout_ms})
    return cls.from_config(cfg, material, config_dir=config_dir, url=url)


def open_cellio(cfg: CellIODevice, url: str | None = None, timeout_ms: float | None = None) -> CellIO:
    """The cell I/O coupler of `devices.cellio` (by its `transport`), not yet connected.

    `url` overrides cfg.url; `timeout_ms` overrides the link watchdog (lost_after_cycles cycles).
    """
    cls = _backend(CELLIO_BACKENDS, cfg.transport, "devices.cellio.transport", "cell I/O transport")
    return cls(url or cfg.url, device_id=cfg.device_id, cycle_ms=cfg.cycle_ms, timeout_ms=timeout_ms,
               lost_after_cycles=cfg.lost_after_cycles)

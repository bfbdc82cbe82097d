"""Wiring the cell's devices from cell.yaml, and the in-process simulators of `--sim`.

`SimHarness` starts every simulator (sims.up.serve_all, ephemeral loopback ports) on a
background thread with its own event loop, so the controller, on its own loop, talks to them
over the real protocols exactly as to hardware. `Devices.open(cfg)` connects the drivers; a
device that does not answer is a `DeviceUnreachable` naming it and its URL (exit 2).
"""
from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Awaitable, TypeVar

from core.config import CellConfig, load_material
from drivers.errors import DeviceError
from drivers.registry import open_cellio, open_cnc, open_power_source, open_robot
from controller.ports import CellIOPort, CncLinkPort, PowerSourcePort, RobotLinkPort
from core.material import Material

T = TypeVar("T")


class DeviceUnreachable(DeviceError):
    """A device of cell.yaml does not answer at its URL."""


def with_urls(cfg: CellConfig, urls: dict[str, str], time_scale: float | None = None) -> CellConfig:
    """A copy of `cfg` whose devices point at `urls` (device -> URL), optionally re-timed."""
    devs = cfg.devices
    upd = {name: getattr(devs, name).model_copy(update={"url": url}) for name, url in urls.items()
           if hasattr(devs, name)}
    out = cfg.model_copy(update={"devices": devs.model_copy(update=upd)})
    if time_scale is not None:
        out = out.model_copy(update={"cell": out.cell.model_copy(update={"time_scale": float(time_scale)})})
    return out


@dataclass
class Devices:
    """The connected drivers of one cell."""

    cfg: CellConfig
    material: Material
    robot: RobotLinkPort | None = None
    cnc: CncLinkPort | None = None
    power: PowerSourcePort | None = None
    cellio: CellIOPort | None = None
    opened: list[RobotLinkPort | CncLinkPort | PowerSourcePort | CellIOPort] = field(default_factory=list)

    def robot_link(self) -> RobotLinkPort:
        """The robot link; a DeviceError naming it when it is not connected."""
        if self.robot is None:
            raise DeviceError(f"robot at {self.cfg.devices.robot.url}: not connected")
        return self.robot

    def cnc_link(self) -> CncLinkPort:
        """The CNC link; a DeviceError naming it when it is not connected."""
        if self.cnc is None:
            raise DeviceError(f"cnc at {self.cfg.devices.cnc.url}: not connected")
        return self.cnc

    def power_source(self) -> PowerSourcePort:
        """The power source; a DeviceError naming it when it is not connected."""
        if self.power is None:
            raise DeviceError(f"power source at {self.cfg.devices.power_source.url}: not connected")
        return self.power

    @property
    def motion(self) -> RobotLinkPort | CncLinkPort | None:
        return self.robot if self.cfg.cell.platform == "robot" else self.cnc

    @classmethod
    async def open(cls, cfg: CellConfig, material: Material | None = None, *,
                   resume_ticket: int | None = None, reply_timeout_ms: float | None = None) -> "Devices":
        """Connect the motion link of the platform, the power source and the cell I/O.

        `reply_timeout_ms` overrides the bus devices' reply timeout (in-process simulators
        share the GIL with the controller, so `--sim` allows them more than hardware gets).
        """
        mat = material or load_material(cfg.cell.material)
        d = cls(cfg, mat)
        try:
            if cfg.cell.platform == "robot":
                r = cfg.devices.robot
                d.robot = open_robot(r, time_scale=cfg.cell.time_scale)
                await _connect("robot", r.url, d.robot.connect(resume_ticket=resume_ticket))
                d.opened.append(d.robot)
            else:
                c = cfg.devices.cnc
                d.cnc = open_cnc(c, time_scale=cfg.cell.time_scale)
                await _connect("cnc", c.url, d.cnc.connect())
                d.opened.append(d.cnc)
            ps = cfg.devices.power_source
            d.power = open_power_source(ps, mat, timeout_ms=reply_timeout_ms)
            await _connect("power_source", ps.url, d.power.connect())
            d.opened.append(d.power)
            io = cfg.devices.cellio
            d.cellio = open_cellio(io, timeout_ms=reply_timeout_ms)
            await _connect("cellio", io.url, d.cellio.connect())
            d.opened.append(d.cellio)
        except BaseException:
            await d.close()
            raise
        return d

    async def close(self) -> None:
        for dev in reversed(self.opened):
            try:
                await dev.close()
            except Exception:
                pass
        self.opened.clear()


async def _connect(device: str, url: str, coro: Awaitable[T], timeout: float = 10.0) -> T:
    try:
        return await asyncio.wait_for(coro, timeout)
    except (asyncio.TimeoutError, OSError, ConnectionError) as exc:
        raise DeviceUnreachable(f"{device} at {url} does not answer ({exc.__class__.__name__}: {exc}); "
                                "is it powered and is `cell sim up` running?") from None
    except DeviceError as exc:
        if device in str(exc) or url in str(exc):
            raise DeviceUnreachable(str(exc)) from None
        raise DeviceUnreachable(f"{device} at {url}: {exc}") from None

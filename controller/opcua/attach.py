"""Serving a controller over OPC UA: its bus for the views, its commands for the methods."""
from __future__ import annotations

import asyncio
from importlib import metadata
from typing import Any

from controller.opcua.server import FactoryServer, Identification


class LoopControl:
    """The controller's pause/resume/abort, called from the OPC UA thread on the controller's loop."""

    def __init__(self, ctl: Any, loop: asyncio.AbstractEventLoop, timeout_s: float = 5.0) -> None:
        self._ctl, self._loop, self._timeout = ctl, loop, timeout_s

    def _call(self, name: str) -> None:
        async def go() -> None:
            getattr(self._ctl, name)()

        asyncio.run_coroutine_threadsafe(go(), self._loop).result(self._timeout)

    def pause(self) -> None:
        self._call("pause")

    def resume(self) -> None:
        self._call("resume")

    def abort(self) -> None:
        self._call("abort")


def software_revision() -> str:
    try:
        return metadata.version("cell-controller")
    except metadata.PackageNotFoundError:
        return "unknown"


async def serve(ctl: Any) -> FactoryServer | None:
    """Start the OPC UA server of a connected controller when cell.yaml enables it (else None)."""
    o = ctl.cfg.opcua
    if not o.enabled:
        return None
    ident = Identification(o.manufacturer, o.model, o.serial_number or ctl.cfg.cell.name, software_revision())
    server = FactoryServer(o, cell_name=ctl.cfg.cell.name, identification=ident, bus=ctl.bus,
                           control=LoopControl(ctl, asyncio.get_running_loop()))
    # the server starts on its own thread; waiting for it (seconds on a loaded machine) on the
    # controller's loop held the device cycles: the robot link was lost while idle
    await asyncio.to_thread(server.start)
    return server

"""A pymodbus 3.16 server whose data are a simulator's own: the small glue both Modbus sims use.

pymodbus calls `async_getValues` / `async_setValues` of the server context for every request;
`DeviceContext` forwards them to a simulator object implementing `read(fc, address, count)`
and `write(fc, address, values)` (return None for an illegal address) and `silent()`. A
request to another device id, or any request while the device is silent, gets no answer at
all (`ignore_missing_devices`), exactly like a dead device on a bus.
"""
from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from typing import Awaitable, Callable, Protocol
from urllib.parse import urlsplit

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.exceptions import NoSuchIdException
from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.base import ModbusBaseServer

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


class ModbusModel(Protocol):
    def read(self, fc: int, address: int, count: int) -> list[int] | list[bool] | None: ...
    def write(self, fc: int, address: int, values: list[int]) -> bool: ...
    def silent(self) -> bool: ...


class TickingModel(ModbusModel, Protocol):
    async def run(self) -> None:
        """Advance the model forever (cancelled on close)."""


class DeviceContext(ModbusServerContext):
    """Server context for one device id backed by a simulator model."""

    def __init__(self, model: ModbusModel, device_id: int = 1) -> None:  # noqa: D107
        # no super().__init__: pymodbus' data blocks are not used (and warn as deprecated)
        self.model = model
        self.device_id = device_id
        self.old_simulator = True
        self.simdevices = []
        self.requests = 0

    def _check(self, device_id: int) -> None:
        if device_id != self.device_id or self.model.silent():
            raise NoSuchIdException(f"device {device_id} does not answer")

    async def async_getValues(self, device_id: int, func_code: int, address: int,
                              count: int = 1) -> list[int] | list[bool] | ExcCodes:
        self._check(device_id)
        out = self.model.read(func_code, address, count)
        return ExcCodes.ILLEGAL_ADDRESS if out is None else out

    async def async_setValues(self, device_id: int, func_code: int, address: int,
                              values: Sequence[int] | Sequence[bool]) -> ExcCodes | None:
        self._check(device_id)
        self.requests += 1
        ok = self.model.write(func_code, address, list(values))
        return None if ok else ExcCodes.ILLEGAL_ADDRESS

    def device_ids(self) -> list[int]:
        return [self.device_id]


async def start_tcp(model: ModbusModel, host: str, port: int, device_id: int = 1) -> tuple[ModbusTcpServer, int]:
    """Serve `model` over Modbus TCP; returns the server and the bound port (port 0: ephemeral)."""
    server = ModbusTcpServer(DeviceContext(model, device_id), address=(host, port),
                             ignore_missing_devices=True)
    await server.serve_forever(background=True)
    return server, _bound_port(server, port)


async def start_rtu(model: ModbusModel, url: str, device_id: int = 1) -> tuple[ModbusSerialServer, str]:
    """Serve `model` over Modbus RTU on a serial URL; `socket://host:port` listens on TCP.

    Returns the server and the URL a driver opens (the real port when port 0 was asked).
    """
    server = ModbusSerialServer(DeviceContext(model, device_id), framer=FramerType.RTU, port=url,
                                ignore_missing_devices=True, baudrate=115200)
    await server.serve_forever(background=True)
    if url.startswith("socket://"):
        parts = urlsplit(url)
        url = f"socket://{parts.hostname}:{_bound_port(server, parts.port or 0)}"
    return server, url


async def serve_tcp(model: TickingModel, host: str = "127.0.0.1", port: int = 0,
                    device_id: int = 1) -> tuple[str, Callable[[], Awaitable[None]]]:
    """Serve `model` over Modbus TCP and start its ticking; returns (url, close)."""
    server, bound = await start_tcp(model, host, port, device_id)
    return f"tcp://{host}:{bound}", _tick(model, server)


async def serve_rtu(model: TickingModel, url: str = "socket://127.0.0.1:0",
                    device_id: int = 1) -> tuple[str, Callable[[], Awaitable[None]]]:
    """Serve `model` over Modbus RTU on a serial URL and start its ticking; returns (url, close)."""
    server, real = await start_rtu(model, url, device_id)
    return real, _tick(model, server)


def _tick(model: TickingModel, server: ModbusBaseServer) -> Callable[[], Awaitable[None]]:
    """Start `model.run()`; the returned close stops it and the server."""
    ticker = asyncio.get_running_loop().create_task(model.run())

    async def close() -> None:
        ticker.cancel()
        await stop(server)
    return close


def _bound_port(server: ModbusBaseServer, asked: int) -> int:
    sockets = getattr(server.transport, "sockets", None)
    if sockets:
        return int(sockets[0].getsockname()[1])
    return asked


async def stop(server: ModbusBaseServer) -> None:
    await server.shutdown()  # type: ignore[no-untyped-call]  # pymodbus 3.16 leaves shutdown() unannotated
    await asyncio.sleep(0)

"""Serve a byte-stream simulator as a serial device: on loopback TCP (`socket://`) or a pty.

A simulator served here implements the ByteSim protocol (attach / feed / detach). Every byte in
both directions passes through a FaultPipe (sims/faults.py): the fault spec and the 8N1 baud
throttle apply exactly as on a real RS-232 cable. One peer at a time, as on a serial port: a new
TCP connection replaces the old one (the simulator keeps its state across connections).
Shared by the robot and CNC simulators.
"""
from __future__ import annotations

import asyncio
import os
import socket
import time
import tty
from typing import TYPE_CHECKING, Callable, Protocol
from urllib.parse import urlparse

from core.errors import ConfigError
from sims.context import Served, SimContext
from sims.faults import FaultPipe, FaultSpec, bytes_per_second

if TYPE_CHECKING:
    from core.config import CncDevice, RobotDevice


class ByteSim(Protocol):
    def attach(self, write: Callable[[bytes], None]) -> None:
        """A peer connected: `write` sends bytes to it."""

    def feed(self, data: bytes) -> None:
        """Bytes arrived from the peer."""

    def detach(self) -> None:
        """The peer went away (cable out); the simulator keeps its state."""


class SerialSim(ByteSim, Protocol):
    """A ByteSim that `serve_serial` starts, closes and hands its server (`sim.server`)."""

    server: SerialServer | None

    def start(self) -> None:
        """Start the simulator's tasks on the running loop."""

    async def close(self) -> None:
        """Stop its tasks and flush its logs."""


def tcp_address(url: str) -> tuple[str, int]:
    """(host, port) of a `socket://host:port` URL; ConfigError otherwise."""
    u = urlparse(url)
    if u.scheme != "socket" or not u.hostname or u.port is None:
        raise ConfigError(f"simulator URL {url!r}: expected socket://HOST:PORT (or use --pty)")
    return u.hostname, u.port


class SerialServer:
    """Serves one ByteSim. `url` is what a driver passes to serial_for_url once started."""

    def __init__(self, sim: ByteSim, *, name: str, spec: FaultSpec | None = None,
                 baud: int | None = 115200, time_scale: float = 1.0) -> None:
        self.sim = sim
        self.name = name
        self.spec = spec or FaultSpec()
        spec_baud = self.spec.value("baud")
        if spec_baud is not None:
            baud = int(spec_baud)
        # The line keeps its rate in simulated time (docs/contract.md §6): at time scale k it carries k
        # times the bytes per wall second, so a time scale never starves a bead that real
        # hardware would not starve.
        self._base_rate = bytes_per_second(baud) if baud else None
        self.rate = self._base_rate * time_scale if self._base_rate else None
        self.url = ""
        self.connections = 0
        self.pipes: tuple[FaultPipe, FaultPipe] | None = None  # (to the sim, from the sim)
        self._server: asyncio.base_events.Server | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._pty: tuple[int, int] | None = None
        self._unplugged_until = 0.0
        self._t0 = time.monotonic()
        self._timers: list[asyncio.TimerHandle] = []

    def set_scale(self, time_scale: float) -> None:
        """The line's rate at a new time scale (the simulators' clock changed), the open
        connection's included."""
        self.rate = self._base_rate * time_scale if self._base_rate else None
        for pipe in self.pipes or ():
            pipe.rate = self.rate

    # -- lifecycle -------------------------------------------------------------------------------
    async def start(self, url: str | None, *, pty: bool = False, ephemeral: bool = False) -> str:
        loop = asyncio.get_running_loop()
        self._t0 = time.monotonic()
        if pty:
            self._start_pty(loop)
        else:
            host, port = tcp_address(url) if url else ("127.0.0.1", 0)
            if ephemeral:
                host, port = "127.0.0.1", 0
            try:
                self._server = await asyncio.start_server(self._on_conn, host, port)
            except OSError as exc:
                raise ConfigError(f"{self.name} simulator: cannot listen on {host}:{port} ({exc.strerror}); "
                                  "is another `cell sim up` running?") from None
            h, p = self._server.sockets[0].getsockname()[:2]
            self.url = f"socket://{h}:{p}"
        for cond, t in self.spec.events("unplug"):
            if cond == "t":
                self._timers.append(loop.call_later(float(t), self.unplug))
        return self.url

    async def close(self) -> None:
        for h in self._timers:
            h.cancel()
        self._drop_current()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        if self._pty is not None:
            asyncio.get_running_loop().remove_reader(self._pty[0])
            for fd in self._pty:
                os.close(fd)
            self._pty = None

    def unplug(self, seconds: float | None = None) -> None:
        """Pull the cable: drop the connection; refuse new ones for `seconds` (spec: unplug=)."""
        if seconds is None:
            seconds = float(self.spec.value("unplug", 0.0))
        self._unplugged_until = time.monotonic() + seconds
        self._drop_current()

    def stall(self, seconds: float) -> None:
        """Both directions stop moving bytes for `seconds` (held, then delivered)."""
        if self.pipes:
            for p in self.pipes:
                p.stall(seconds)

    # -- plumbing --------------------------------------------------------------------------------
    def _make_pipes(self, to_peer: Callable[[bytes], None], alive: Callable[[], bool]) -> FaultPipe:
        """The pipes of a new peer (`self.pipes`); returns the inbound one (to the simulator)."""
        n = self.connections
        self.connections += 1

        def to_sim(data: bytes) -> None:
            if alive():
                self.sim.feed(data)

        def to_wire(data: bytes) -> None:
            if alive():
                to_peer(data)

        t0 = self._t0
        inbound = FaultPipe(to_sim, self.spec, stream=f"{self.name}.in.{n}", rate=self.rate, t0=t0)
        outbound = FaultPipe(to_wire, self.spec, stream=f"{self.name}.out.{n}", rate=self.rate, t0=t0)
        self.pipes = (inbound, outbound)
        self.sim.attach(outbound.send)
        return inbound

    def _drop_current(self) -> None:
        if self._writer is not None:
            w, self._writer = self._writer, None
            w.close()
            self.sim.detach()
        if self.pipes is not None and self._pty is None:
            for p in self.pipes:
                p.close()
            self.pipes = None

    async def _on_conn(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if time.monotonic() < self._unplugged_until:
            writer.close()
            return
        self._drop_current()
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._writer = writer
        inbound = self._make_pipes(writer.write, lambda: self._writer is writer)
        try:
            while True:
                data = await reader.read(4096)
                if not data or self._writer is not writer:
                    break
                inbound.send(data)
        except (ConnectionError, OSError):
            pass
        finally:
            if self._writer is writer:
                self._drop_current()

    def _start_pty(self, loop: asyncio.AbstractEventLoop) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._pty = (master, slave)  # the slave fd stays open: no EIO when a client closes
        self.url = os.ttyname(slave)

        def write(data: bytes) -> None:
            try:
                os.write(master, data)
            except (BlockingIOError, OSError):
                pass  # nobody reading: bytes fall on the floor, as on a real line

        self._make_pipes(write, lambda: self._pty is not None)

        def readable() -> None:
            try:
                data = os.read(master, 4096)
            except (BlockingIOError, OSError):
                return
            if data and self.pipes:
                self.pipes[0].send(data)

        loop.add_reader(master, readable)


async def serve_serial(sim: SerialSim, device: str, dev_cfg: RobotDevice | CncDevice, ctx: SimContext,
                       spec: FaultSpec, extra: dict[str, object]) -> list[Served]:
    """Start `sim` and serve it on `dev_cfg.url` (or port 0 / a pty, per ctx): the tail of a
    serial simulator's `serve(ctx)`. The simulator is closed again if the server cannot start."""
    sim.start()
    server = SerialServer(sim, name=device, spec=spec, baud=dev_cfg.baud, time_scale=ctx.clock.time_scale)
    ctx.clock.watch(server.set_scale)
    sim.server = server  # tests pull the cable with sim.server.unplug()
    try:
        url = await server.start(dev_cfg.url, pty=ctx.pty, ephemeral=ctx.ephemeral)
    except BaseException:
        await sim.close()
        raise

    async def close() -> None:
        await server.close()
        await sim.close()

    return [Served(device, url, close, sim=sim, extra={"baud": dev_cfg.baud, **extra})]

"""`cell sim up`'s clock line (wire/sim_clock.py): a command lowers the simulated time scale to what it can feed,
and a test or `cell run --fault` injects a seeded fault now (sims/inject.py).

Served on an ephemeral loopback port; its address goes into the runtime directory under the CNC's
URL (`clock_file`), so the command that talks to these simulators finds it, and two `cell sim up`
of two cells never meet. The file is removed when the simulators stop.
"""
from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path

from typing import Callable

from sims.clock import SimClock
from wire.sim_clock import OK, Inject, answer, clock_file, error, parse_request

Injector = Callable[[Inject], None]   # raises ValueError naming what the device takes


class ClockServer:
    """Answers SCALE? / SCALE k for one SimClock, and INJECT through `inject` (on the simulators' loop)."""

    def __init__(self, clock: SimClock, cnc_url: str, directory: Path, inject: Injector | None = None) -> None:
        self.clock = clock
        self.inject = inject
        self.cnc_url = cnc_url
        self.path = clock_file(directory, cnc_url)
        self.url = ""
        self._server: asyncio.base_events.Server | None = None

    async def start(self) -> str:
        self._server = await asyncio.start_server(self._on_conn, "127.0.0.1", 0)
        host, port = self._server.sockets[0].getsockname()[:2]
        self.url = f"tcp://{host}:{port}"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + f".{os.getpid()}")
        tmp.write_text(json.dumps({"pid": os.getpid(), "url": self.url, "cnc": self.cnc_url}))
        tmp.replace(self.path)
        return self.url

    async def _on_conn(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                req = parse_request(line)
                if isinstance(req, str):
                    writer.write(error(req))
                elif isinstance(req, Inject):
                    writer.write(self._inject(req))
                else:
                    if req is not None:
                        self.clock.set_scale(req)
                    writer.write(answer(self.clock.time_scale))
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()

    def _inject(self, req: Inject) -> bytes:
        if self.inject is None:
            return error("these simulators take no injected fault")
        try:
            self.inject(req)
        except ValueError as exc:
            return error(str(exc))
        return OK

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        try:
            if json.loads(self.path.read_text()).get("pid") == os.getpid():
                self.path.unlink()
        except (OSError, ValueError):
            pass

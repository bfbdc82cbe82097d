"""Serving a controller over OPC UA from a process of its own (controller.opcua.child).

The controller's side: its bus's latest snapshot goes down a pipe (coalesced), method calls come
back up another and run on the controller's loop. The controller's interpreter does no OPC UA
work at all, so a client cannot slow its device cycles (docs/opcua.md has the measurement).
"""
from __future__ import annotations

import asyncio
import multiprocessing
import threading
import time
from importlib import metadata
from typing import Any

from controller.opcua.child import run as child_run
from controller.opcua.endpoint import PUBLISH_PERIOD_S, START_TIMEOUT_S, Identification, check_endpoint
from core.config import OpcUaSettings
from core.errors import CellError

MIN_SEND_PERIOD_S = PUBLISH_PERIOD_S / 2


class LoopControl:
    """The controller's pause/resume/abort, called from another thread on the controller's loop."""

    def __init__(self, ctl: Any, loop: asyncio.AbstractEventLoop, timeout_s: float = 5.0) -> None:
        self._ctl, self._loop, self._timeout = ctl, loop, timeout_s

    def call(self, name: str) -> None:
        if name not in ("pause", "resume", "abort"):
            raise CellError(f"OPC UA: no command {name!r}")

        async def go() -> None:
            getattr(self._ctl, name)()

        asyncio.run_coroutine_threadsafe(go(), self._loop).result(self._timeout)


def software_revision() -> str:
    try:
        return metadata.version("cell-controller")
    except metadata.PackageNotFoundError:
        return "unknown"


class OpcuaProcess:
    """The OPC UA server's process, fed from `bus`; `start()` returns once clients can connect."""

    def __init__(self, opcua: OpcUaSettings, *, cell_name: str, identification: Identification, bus: Any,
                 control: LoopControl | None) -> None:
        check_endpoint(opcua)   # a bad endpoint is named here, before a process is started
        self.cfg, self.cell_name, self.ident, self.bus = opcua, cell_name, identification, bus
        self.control = control if opcua.allow_control else None
        self.endpoint: str = opcua.endpoint
        self._proc: Any = None
        self._snaps: Any = None
        self._ctrl: Any = None
        self._send_lock = threading.Lock()
        self._changed = threading.Event()
        self._closing = False
        self._unsubscribe: Any = None
        self._threads: list[threading.Thread] = []

    def start(self, timeout_s: float = START_TIMEOUT_S) -> str:
        ctx = multiprocessing.get_context("forkserver")
        snaps_r, self._snaps = ctx.Pipe(duplex=False)
        self._ctrl, ctrl_child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=child_run, name="cell-opcua", daemon=True,
                                 args=(snaps_r, ctrl_child, self.cfg, self.cell_name, self.ident, self.bus.latest))
        self._proc.start()
        snaps_r.close()
        ctrl_child.close()
        if not self._ctrl.poll(timeout_s):
            self.stop()
            raise CellError(f"OPC UA server at {self.endpoint} did not start within {timeout_s:.0f} s")
        try:
            msg = self._ctrl.recv()
        except (EOFError, OSError):
            msg = ("error", f"its process exited (code {self._proc.exitcode})")
        if msg[0] != "ready":
            self.stop()
            raise CellError(f"OPC UA server at {self.endpoint} cannot start ({msg[1]}); check opcua in cell.yaml")
        self._unsubscribe = self.bus.subscribe(lambda _s: self._changed.set())
        for target, name in ((self._feed, "opcua-feed"), (self._answer, "opcua-control")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self.endpoint

    def _feed(self) -> None:
        """Send the latest snapshot when it changed, at most every MIN_SEND_PERIOD_S."""
        last = 0.0
        while not self._closing:
            if not self._changed.wait(0.5):
                continue
            wait = last + MIN_SEND_PERIOD_S - time.monotonic()
            if wait > 0:
                time.sleep(wait)   # changes in the meantime ride along: latest wins
            self._changed.clear()
            last = time.monotonic()
            try:
                with self._send_lock:
                    if self._closing:
                        return
                    self._snaps.send(("snap", self.bus.latest))
            except (OSError, ValueError):
                return   # the child is gone

    def _answer(self) -> None:
        """Run the child's method calls on the controller; send each one's outcome back."""
        while True:
            try:
                msg = self._ctrl.recv()
            except (EOFError, OSError):
                return
            if msg[0] != "call":
                continue
            error: str | None = None
            try:
                if self.control is None:
                    raise CellError("control over OPC UA is off (opcua.allow_control: false)")
                self.control.call(msg[2])
            except Exception as exc:   # the refusal goes to the client as BadInvalidState
                error = str(exc) or type(exc).__name__
            try:
                self._ctrl.send(("done", msg[1], error))
            except (OSError, ValueError):
                return

    def stop(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        self._closing = True
        self._changed.set()
        if self._snaps is not None:
            with self._send_lock:
                try:
                    self._snaps.send(("stop",))
                except (OSError, ValueError):
                    pass
        if self._proc is not None:
            self._proc.join(10.0)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(5.0)
            self._proc = None
        for conn in (self._snaps, self._ctrl):
            if conn is not None:
                conn.close()
        for t in self._threads:
            t.join(2.0)
        self._threads.clear()


async def serve(ctl: Any) -> OpcuaProcess | None:
    """Start the OPC UA server of a connected controller when cell.yaml enables it (else None)."""
    o = ctl.cfg.opcua
    if not o.enabled:
        return None
    ident = Identification(o.manufacturer, o.model, o.serial_number or ctl.cfg.cell.name, software_revision())
    server = OpcuaProcess(o, cell_name=ctl.cfg.cell.name, identification=ident, bus=ctl.bus,
                          control=LoopControl(ctl, asyncio.get_running_loop()))
    # starting takes seconds (a process, asyncua's imports, the bind): never on the controller's loop
    await asyncio.to_thread(server.start)
    return server

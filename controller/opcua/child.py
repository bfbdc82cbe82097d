"""The OPC UA server's own process: a bus fed from the controller's pipe, commands sent back.

Measured in-process (asyncua on a thread of the controller), the server's Python work shared the
controller's interpreter lock and added 10-16 ms to the p99 device-cycle period (docs/opcua.md).
Here it runs in a process of its own: the controller only pickles the latest snapshot onto a pipe
(coalesced, at most every PUBLISH_PERIOD_S / 2) and answers method calls that come back on a
second pipe. This module is the child's side; `controller.opcua.attach` is the controller's.

Messages (pickled tuples):
  snapshots pipe, controller → child: `("snap", Snapshot)`, `("stop",)`
  control pipe, child → controller: `("ready", endpoint)`, `("error", message)`,
                                   `("call", id, command)`
  control pipe, controller → child: `("done", id, None | message)`
"""
from __future__ import annotations

import itertools
import threading
from typing import Any

from controller.runtime.events import EventBus, Snapshot
from core.config import OpcUaSettings
from core.errors import CellError
import os

CALL_TIMEOUT_S = 10.0


class PipeControl:
    """Pause/Resume/Abort sent to the controller over the control pipe; raises its refusal."""

    def __init__(self, conn: Any) -> None:
        self._conn = conn
        self._ids = itertools.count(1)
        self._send_lock = threading.Lock()
        self._waiting: dict[int, threading.Event] = {}
        self._refusals: dict[int, str | None] = {}

    def _call(self, command: str) -> None:
        n = next(self._ids)
        done = self._waiting[n] = threading.Event()
        self.send(("call", n, command))
        if not done.wait(CALL_TIMEOUT_S):
            self._waiting.pop(n, None)
            raise CellError(f"the controller did not answer {command} within {CALL_TIMEOUT_S:.0f} s")
        refusal = self._refusals.pop(n, None)
        if refusal is not None:
            raise CellError(refusal)

    def answered(self, n: int, error: str | None) -> None:
        done = self._waiting.pop(n, None)
        if done is not None:
            self._refusals[n] = error
            done.set()

    def send(self, msg: tuple[Any, ...]) -> None:
        with self._send_lock:
            self._conn.send(msg)

    def pause(self) -> None:
        self._call("pause")

    def resume(self) -> None:
        self._call("resume")

    def abort(self) -> None:
        self._call("abort")


def run(snaps: Any, control: Any, opcua: OpcUaSettings, cell_name: str, ident: Any, initial: Snapshot) -> None:
    """Child entry point: serve until the controller says stop or its pipe closes."""

    # lazy: OPC UA loads only when cell.yaml enables it
    from controller.opcua.server import FactoryServer

    try:
        os.nice(5)   # below the simulators and the controller when they share a CPU
    except OSError:
        pass
    bus = EventBus(initial)   # a copy of the controller's, replaced whole by every snapshot it sends
    ctl = PipeControl(control)
    try:
        server = FactoryServer(opcua, cell_name=cell_name, identification=ident, bus=bus, control=ctl)
        endpoint = server.start()
    except Exception as exc:  # told to the controller, which raises it in its own words
        ctl.send(("error", str(exc)))
        return

    def answers() -> None:
        try:
            while True:
                msg = control.recv()
                if msg[0] == "done":
                    ctl.answered(msg[1], msg[2])
        except (EOFError, OSError):
            return

    threading.Thread(target=answers, name="opcua-answers", daemon=True).start()
    ctl.send(("ready", endpoint))
    try:
        while True:
            msg = snaps.recv()
            if msg[0] == "stop":
                break
            bus.publish(msg[1])
    except (EOFError, OSError):
        pass   # the controller went away: stop serving
    finally:
        server.stop()

"""The factory interface (docs/contract.md §8): an OPC UA client watches a simulated build.

The server is fed by the controller's own event bus; the client is asyncua's, on the real
OPC UA binary protocol over loopback TCP, as a factory's MES would connect.
"""
from __future__ import annotations

import asyncio
import math
import socket
import time
from pathlib import Path

import pytest
from asyncua import Client, ua

from controller.job.read import job_from_dict
from core.config import OpcUaSettings, load_cell, load_sim
from controller.opcua.endpoint import Identification
from controller.opcua.server import FactoryServer
from controller.runtime.events import EventBus
from core.errors import ConfigError
from tests.cells import small_job
from controller.defaults import SIM_REPLY_TIMEOUT_MS
from controller.harness.cell import open_cell, with_urls

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


def _endpoint() -> str:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return f"opc.tcp://127.0.0.1:{port}/cell"


class OpcCell:
    """Simulators in-process, a controller serving OPC UA, and an asyncua client connected to it."""

    def __init__(self, tmp: Path, *, allow_control: bool, scale: float = 10.0) -> None:
        cfg = with_urls(load_cell(), {}, time_scale=scale)
        self.endpoint = _endpoint()
        cfg = cfg.model_copy(update={"opcua": OpcUaSettings(enabled=True, endpoint=self.endpoint,
                                                            allow_control=allow_control)})
        self._open = open_cell(cfg, sim=load_sim(), log_dir=tmp / "log", runs_dir=tmp / "runs",
                               reply_timeout_ms=SIM_REPLY_TIMEOUT_MS)
        self.client = Client(self.endpoint)

    async def __aenter__(self) -> "OpcCell":
        self.ctl = await self._open.__aenter__()
        self.harness = self.ctl.simulators
        await self.client.connect()
        ns = await self.client.get_namespace_index("urn:cell-controller:machines")
        self.machine = await self.client.nodes.objects.get_child([f"{ns}:Machines", f"{ns}:demo-cell"])
        self.ns = ns
        return self

    async def node(self, *path: str):
        return await self.machine.get_child([f"{self.ns}:{p}" for p in path])

    async def __aexit__(self, *exc: object) -> None:
        await self.client.disconnect()
        await self._open.__aexit__(*exc)


class Recorder:
    """Data-change and event handler: what the client was told, with the time it was told."""

    def __init__(self) -> None:
        self.values: dict[str, list[tuple[float, object]]] = {}
        self.events: list[tuple[float, object]] = []
        self.names: dict[object, str] = {}

    def datachange_notification(self, node, val, data) -> None:
        self.values.setdefault(self.names[node.nodeid], []).append((time.monotonic(), val))

    def event_notification(self, event) -> None:
        self.events.append((time.monotonic(), event))


async def test_a_client_follows_a_build_and_gets_the_door_alarm_as_an_event(tmp_path: Path) -> None:
    async with OpcCell(tmp_path, allow_control=False) as c:
        rec = Recorder()
        sub = await c.client.create_subscription(20, rec)
        watched = {"State": await c.node("State"), "PassesDone": await c.node("JobManagement", "PassesDone"),
                   "LayersDone": await c.node("JobManagement", "LayersDone"),
                   "Current": await c.node("Monitoring", "Process", "Current"),
                   "Voltage": await c.node("Monitoring", "Process", "Voltage"),
                   "ArcOn": await c.node("Monitoring", "Process", "ArcOn")}
        for name, n in watched.items():
            rec.names[n.nodeid] = name
        await sub.subscribe_data_change(list(watched.values()))
        etype = await c.client.nodes.base_event_type.get_child(f"{c.ns}:CellAlarmEventType")
        await sub.subscribe_events(c.machine, etype)
        ident = await c.node("Identification", "SoftwareRevision")
        assert (await ident.read_value()) not in ("", None)
        # without allow_control the methods are not in the address space
        names = {(await m.read_browse_name()).Name for m in await c.machine.get_methods()}
        assert names == set()
        job = small_job(n_layers=3)
        c.ctl.open_job(job_from_dict(job))
        c.ctl.trace = c.ctl.trace.given(wire_lot="HX-77", operator="A. Welder")   # as `--wire-lot` gives it
        res = await asyncio.wait_for(c.ctl.start(), 60)
        assert res.state == "complete"
        await asyncio.sleep(0.3)
        # the running job's feedstock lot (OPC 40540) and operator (docs/records.md)
        assert await (await c.node("JobManagement", "WireLot")).read_value() == "HX-77"
        assert await (await c.node("JobManagement", "Operator")).read_value() == "A. Welder"
        states = [v for _, v in rec.values["State"]]
        assert states[0] == "ready" or "idle" in states
        assert any(s.startswith("running") for s in states) and states[-1] == "complete"
        assert states.index("complete") > max(i for i, s in enumerate(states) if s.startswith("running"))
        done = [v for _, v in rec.values["PassesDone"]]
        assert done == sorted(done) and done[-1] == 6 and len(set(done)) >= 4
        currents = [v for _, v in rec.values["Current"] if not math.isnan(v)]
        volts = [v for _, v in rec.values["Voltage"] if not math.isnan(v)]
        assert len(set(round(x, 1) for x in currents)) >= 3 and max(currents) > 80   # the arc's current moved
        assert len(set(round(x, 2) for x in volts)) >= 3
        assert True in [v for _, v in rec.values["ArcOn"]]

        # a door opened during the next build: the alarm arrives as an event within 100 ms
        c.ctl.open_job(job_from_dict(small_job(n_layers=2, side=24.0)))
        build = asyncio.ensure_future(c.ctl.start())
        t0 = time.monotonic()
        while c.ctl.snapshot().state != "running_depositing":
            assert time.monotonic() - t0 < 30
            await asyncio.sleep(0.002)
        n_alarms = len(c.ctl.snapshot().alarms)
        before = len(rec.events)
        c.harness.call(c.harness.sim("cellio").open_door)
        while len(c.ctl.snapshot().alarms) == n_alarms:
            assert time.monotonic() - t0 < 30
            await asyncio.sleep(0.001)
        t_alarm = time.monotonic()
        await asyncio.wait_for(build, 20)
        await asyncio.sleep(0.3)
        new = rec.events[before:]
        assert new, "no OPC UA event for the door alarm"
        t_event, ev = new[0]
        assert t_event - t_alarm < 0.100
        assert "door" in ev.Message.Text.lower()
        assert ev.Layer == 0 and ev.Pass >= 0


async def test_abort_method_only_with_allow_control_and_it_stops_at_the_end_of_the_bead(tmp_path: Path) -> None:
    async with OpcCell(tmp_path, allow_control=True, scale=5.0) as c:
        names = {(await m.read_browse_name()).Name for m in await c.machine.get_methods()}
        assert names == {"Pause", "Resume", "Abort"}
        abort = await c.machine.get_child([f"{c.ns}:Abort"])
        job = small_job(n_layers=3)
        c.ctl.open_job(job_from_dict(job))
        build = asyncio.ensure_future(c.ctl.start())
        t0 = time.monotonic()
        while c.ctl.snapshot().state != "running_depositing":
            assert time.monotonic() - t0 < 30
            await asyncio.sleep(0.002)
        await c.machine.call_method(abort)
        assert c.ctl.snapshot().state == "running_depositing"        # the bead goes on to its end
        res = await asyncio.wait_for(build, 30)
        assert res.state == "aborted" and res.passes_done == 1
        with pytest.raises(ua.UaStatusCodeError):                   # nothing to abort any more
            await c.machine.call_method(abort)


def test_an_endpoint_off_the_host_needs_certificates_and_users() -> None:
    cfg = OpcUaSettings(enabled=True, endpoint="opc.tcp://0.0.0.0:4840/cell")
    with pytest.raises(ConfigError, match="leaves the host"):
        FactoryServer(cfg, cell_name="c", identification=Identification("m", "m", "s", "r"),
                      bus=EventBus(), control=None)


def test_the_controller_process_never_imports_asyncua() -> None:
    """asyncua lives in the server's own process: imported by the controller (300 ms on the loop,
    and its objects in every garbage collection) it stalled the device cycles once per build."""
    import subprocess
    import sys

    code = ("import sys, controller.api, controller.opcua.attach, controller.cli.run; "
            "print('asyncua' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.strip() == "False", out.stderr[-2000:]

"""OPC UA server of one cell, fed by the controller's event bus (docs/contract.md §8).

Runs asyncua on a thread and loop of its own; the controller runs it in a process of its own
(controller.opcua.child, fed over a pipe) so it never shares the controller's interpreter lock.
It reads only the bus's snapshots (the same events the TUI and the progress lines render) and
calls the controller's commands through a `ControlPort` whose methods are safe to call from
another thread.

Node tree (modelled on OPC 40540 and OPC UA for Machinery), under Objects/Machines/<cell name>/:
Identification (Manufacturer, Model, SerialNumber, SoftwareRevision), Monitoring/Process
(Current, Voltage, WireFeedSpeed, TravelSpeed, PartTemperature, ArcOn, StickOut,
LayerHeightError, ZCorrection), State, JobManagement
(JobName, JobHash, LayersTotal, LayersDone, PassesTotal, PassesDone, Layer, Pass), alarms as
CellAlarmEventType events (Layer, Pass, PositionX/Y/Z, Kind) emitted by the machine object, and
methods Pause, Resume, Abort only with `allow_control: true`.
"""
from __future__ import annotations

import asyncio
import logging
import threading
from typing import Any, Callable, Protocol

from asyncua import Server, ua

from controller.runtime.events import Alarm, EventBus, Snapshot
from controller.opcua.endpoint import PUBLISH_PERIOD_S, START_TIMEOUT_S, Identification, check_endpoint
from controller.opcua.security import PasswordUsers
from core.config import OpcUaSettings
from core.errors import CellError

NAMESPACE = "urn:cell-controller:machines"
log = logging.getLogger(__name__)


class ControlPort(Protocol):
    """The controller commands OPC UA may call, each safe to call from another thread."""

    def pause(self) -> None: ...
    def resume(self) -> None: ...
    def abort(self) -> None: ...


PROCESS = {  # node name → (snapshot field, OPC UA type)
    "Current": ("current_a", ua.VariantType.Double),
    "Voltage": ("voltage_v", ua.VariantType.Double),
    "WireFeedSpeed": ("wfs_m_min", ua.VariantType.Double),
    "TravelSpeed": ("travel_speed_mm_min", ua.VariantType.Double),
    "PartTemperature": ("temperature_c", ua.VariantType.Double),
    "ArcOn": ("arc_on", ua.VariantType.Boolean),
    "StickOut": ("stick_out_mm", ua.VariantType.Double),             # CTWD estimate (docs/closed-loop.md)
    "LayerHeightError": ("layer_height_error_mm", ua.VariantType.Double),  # last layer's top − plan
    "ZCorrection": ("z_correction_mm", ua.VariantType.Double),       # z offset of the current layer
    "PathHeightRms": ("path_rms_mm", ua.VariantType.Double),         # path loop: last layer's RMS along the path
    "PathHeightSpread": ("path_spread_mm", ua.VariantType.Double),   # ... its top's spread along the path
    "PathSpeedFactorMin": ("path_factor_min", ua.VariantType.Double),  # current layer's per-segment speed factors
    "PathSpeedFactorMax": ("path_factor_max", ua.VariantType.Double),
}
JOB = {
    "JobName": ("job_name", ua.VariantType.String),
    "JobHash": ("job_hash", ua.VariantType.String),
    "WireLot": ("wire_lot", ua.VariantType.String),      # the feedstock lot of the running job (OPC 40540)
    "ShieldingGas": ("gas", ua.VariantType.String),
    "Operator": ("operator", ua.VariantType.String),
    "LayersTotal": ("layers_total", ua.VariantType.Int32),
    "LayersDone": ("layers_done", ua.VariantType.Int32),
    "PassesTotal": ("passes_total", ua.VariantType.Int32),
    "PassesDone": ("passes_done", ua.VariantType.Int32),
    "Layer": ("layer", ua.VariantType.Int32),
    "Pass": ("pass_", ua.VariantType.Int32),
}
_EMPTY = {ua.VariantType.Double: float("nan"), ua.VariantType.Boolean: False,
          ua.VariantType.String: "", ua.VariantType.Int32: -1}


def _value(snap: Snapshot, field: str, vtype: ua.VariantType) -> Any:
    v = getattr(snap, field, None)
    if v is None:
        return _EMPTY[vtype]   # not sampled: NaN / -1 / "" rather than a stale number
    if vtype is ua.VariantType.Double:
        return float(v)
    if vtype is ua.VariantType.Int32:
        return int(v)
    if vtype is ua.VariantType.Boolean:
        return bool(v)
    return str(v)


class FactoryServer:
    """Serve one cell's snapshots over OPC UA; `start()` returns once clients can connect."""

    def __init__(self, opcua: OpcUaSettings, *, cell_name: str, identification: Identification, bus: EventBus,
                 control: ControlPort | None) -> None:
        self.cfg = opcua
        self.cell_name = cell_name
        self.ident = identification
        self.bus = bus
        self.control = control if opcua.allow_control else None
        self.endpoint = opcua.endpoint
        self._secured = check_endpoint(opcua)
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._wake: asyncio.Event | None = None
        self._unsubscribe: Callable[[], None] | None = None

    # -- life cycle (any thread) -------------------------------------------------------------------
    def start(self, timeout_s: float = START_TIMEOUT_S) -> str:
        self._thread = threading.Thread(target=self._run, name="opcua", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise CellError(f"OPC UA server at {self.endpoint} did not start within {timeout_s:.0f} s")
        if self._error is not None:
            err = self._error
            raise CellError(f"OPC UA server at {self.endpoint} cannot start ({err}); check opcua in cell.yaml") from None
        return self.endpoint

    def stop(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        if self._loop is not None and self._stop is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(10.0)
            self._thread = None

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported to start(); the controller goes on without OPC UA
            self._error = exc
            self._ready.set()

    # -- the server's own loop ---------------------------------------------------------------------
    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop, self._wake = asyncio.Event(), asyncio.Event()
        server = await self._build()
        async with server:
            self._unsubscribe = self.bus.subscribe(lambda _s: self._poke())
            self._ready.set()
            await self._publish_loop()

    def _poke(self) -> None:
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None and not loop.is_closed():
            loop.call_soon_threadsafe(wake.set)

    async def _build(self) -> Server:
        users = PasswordUsers(dict(self.cfg.users)) if self._secured else None
        server = Server(user_manager=users) if users else Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"cell controller {self.cell_name}")
        if self._secured:
            cert, key = self.cfg.certificate, self.cfg.private_key
            assert cert is not None and key is not None  # check_endpoint: secured means both are set
            await server.load_certificate(cert)
            await server.load_private_key(key)
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
            server.set_identity_tokens([ua.UserNameIdentityToken])
        else:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        idx = await server.register_namespace(NAMESPACE)
        machines = await server.nodes.objects.add_folder(idx, "Machines")
        self.machine = await machines.add_object(idx, self.cell_name)
        await self.machine.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        ident = await self.machine.add_object(idx, "Identification")
        for name, val in (("Manufacturer", self.ident.manufacturer), ("Model", self.ident.model),
                          ("SerialNumber", self.ident.serial_number),
                          ("SoftwareRevision", self.ident.software_revision)):
            await ident.add_property(idx, name, val)
        process = await (await self.machine.add_object(idx, "Monitoring")).add_object(idx, "Process")
        jobs = await self.machine.add_object(idx, "JobManagement")
        self._nodes: dict[str, tuple[Any, str, ua.VariantType]] = {}
        snap = self.bus.latest
        for parent, table in ((process, PROCESS), (jobs, JOB)):
            for name, (field, vt) in table.items():
                node = await parent.add_variable(idx, name, ua.Variant(_value(snap, field, vt), vt))
                self._nodes[name] = (node, field, vt)
        state = await self.machine.add_variable(idx, "State", ua.Variant(str(snap.state), ua.VariantType.String))
        self._nodes["State"] = (state, "state", ua.VariantType.String)
        etype = await server.create_custom_event_type(
            idx, "CellAlarmEventType", ua.ObjectIds.BaseEventType,
            [("Kind", ua.VariantType.String), ("Layer", ua.VariantType.Int32), ("Pass", ua.VariantType.Int32),
             ("PositionX", ua.VariantType.Double), ("PositionY", ua.VariantType.Double),
             ("PositionZ", ua.VariantType.Double)])
        self._events = await server.get_event_generator(etype, self.machine.nodeid)
        if self.control is not None:
            for name in ("Pause", "Resume", "Abort"):
                await self.machine.add_method(idx, name, self._method(name.lower()), [], [])
        self._last: dict[str, Any] = {}
        self._alarms_sent = len(snap.alarms)
        return server

    def _method(self, command: str) -> Callable[..., Any]:
        assert self.control is not None
        fn = getattr(self.control, command)

        async def call(_parent: Any) -> list[ua.Variant]:
            try:
                await asyncio.get_running_loop().run_in_executor(None, fn)
            except CellError as exc:
                log.info("OPC UA %s refused: %s", command, exc)
                # asyncua leaves UaStatusCodeError's constructor unannotated
                raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidState) from None  # type: ignore[no-untyped-call]
            return []

        return call

    async def _publish_loop(self) -> None:
        assert self._stop is not None and self._wake is not None
        while not self._stop.is_set():
            try:
                await asyncio.wait_for(self._wake.wait(), PUBLISH_PERIOD_S)
            except TimeoutError:
                pass
            self._wake.clear()
            await self._publish(self.bus.latest)

    async def _publish(self, snap: Snapshot) -> None:
        for alarm in snap.alarms[self._alarms_sent:]:
            await self._fire(alarm)
        self._alarms_sent = len(snap.alarms)
        for name, (node, field, vt) in self._nodes.items():
            v = _value(snap, field, vt) if name != "State" else str(snap.state)
            if self._last.get(name, object()) != v or v != v:   # NaN never equals itself: write once
                if v != v and isinstance(self._last.get(name), float) and self._last[name] != self._last[name]:
                    continue
                await node.write_value(ua.Variant(v, vt))
                self._last[name] = v

    async def _fire(self, a: Alarm) -> None:
        ev = self._events.event
        ev.Message = ua.LocalizedText(a.message)
        ev.Severity = 900 if a.kind in ("fault", "estop") else 500
        ev.Kind = a.kind
        ev.Layer = -1 if a.layer is None else int(a.layer)
        ev.Pass = -1 if a.pass_ is None else int(a.pass_)
        x, y, z = a.position if a.position is not None else (float("nan"),) * 3
        ev.PositionX, ev.PositionY, ev.PositionZ = float(x), float(y), float(z)
        await self._events.trigger(message=a.message)

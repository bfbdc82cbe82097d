"""Power source over CAN: python-can for the bus, cantools for config/power_source.dbc.

Each 10 ms cycle the host sends `WELD_CMD` (0x200+n) with an incremented 8-bit alive counter
and waits for `WELD_STATUS` (0x180+n) and `WELD_ACTUALS` (0x280+n) echoing that counter. The
DBC describes node 1; node n shifts every id by n-1. No reply within `timeout_ms` is a lost
link (LinkLost naming the interface and channel); a frame is never re-sent.

Buses: any python-can interface. `virtual` (in-process, tests), `udp_multicast` (between
processes on one host: `cell sim up` and the controller), `socketcan` on real hardware.
"""
from __future__ import annotations

import asyncio
from pathlib import Path

from drivers.errors import DeviceError, LinkLost
from drivers.power import PowerCommand, PowerSource
from planner.errors import ConfigError

_CMD_BITS = {"weld_start": "WeldStart", "robot_ready": "RobotReady", "error_reset": "ErrorReset",
             "gas_test": "GasTest", "wire_inch": "WireInch", "wire_retract": "WireRetract"}
_STATUS_BITS = {"heartbeat": "Heartbeat", "ready": "Ready", "arc_stable": "ArcStable",
                "current_flow": "CurrentFlow", "main_current": "MainCurrent",
                "collision_ok": "CollisionOK", "gas_fault": "GasFault", "wire_out": "WireOut",
                "process_active": "ProcessActive", "motion_release": "MotionRelease",
                "wire_stick": "WireStick"}
DEFAULT_DBC = Path(__file__).resolve().parent.parent / "config" / "power_source.dbc"


def dbc_path(name: str, config_dir: str | Path | None = None) -> Path:
    """cell.yaml's `can.dbc` (relative to the config directory) as a path that exists."""
    p = Path(name)
    if not p.is_absolute():
        p = Path(config_dir or DEFAULT_DBC.parent) / p
    if not p.exists():
        raise ConfigError(f"devices.power_source.can.dbc: '{p}' not found; point it at power_source.dbc")
    return p


class CanCodec:
    """Encode/decode the three frames of node `node` with a cantools database."""

    def __init__(self, db, node: int = 1) -> None:
        try:
            self.cmd = db.get_message_by_name("WELD_CMD")
            self.sta = db.get_message_by_name("WELD_STATUS")
            self.act = db.get_message_by_name("WELD_ACTUALS")
        except KeyError as exc:
            raise ConfigError(f"power_source.dbc: message {exc} missing (need WELD_CMD, WELD_STATUS, WELD_ACTUALS)") from None
        off = node - 1
        self.cmd_id = self.cmd.frame_id + off
        self.sta_id = self.sta.frame_id + off
        self.act_id = self.act.frame_id + off
        for m, base in ((self.cmd, 0x200), (self.sta, 0x180), (self.act, 0x280)):
            if m.frame_id != base + 1:
                raise ConfigError(f"power_source.dbc: {m.name} has id 0x{m.frame_id:X}, expected 0x{base + 1:X} for node 1")

    def encode_command(self, cmd: PowerCommand, counter: int) -> bytes:
        sig = {v: int(getattr(cmd, k)) for k, v in _CMD_BITS.items()}
        sig.update(Mode=cmd.mode, Job=cmd.job, WFS=round(cmd.wfs_m_min, 2), ArcTrim=round(cmd.arc_trim, 1),
                   DynamicTrim=round(cmd.dynamic_trim, 1), AliveCounter=counter & 0xFF)
        return self.cmd.encode(sig)

    def decode_command(self, data: bytes) -> dict:
        s = self.cmd.decode(data, decode_choices=False)
        return {"bits": {k: bool(s[v]) for k, v in _CMD_BITS.items()}, "mode": int(s["Mode"]),
                "job": int(s["Job"]), "wfs": float(s["WFS"]), "arc_trim": float(s["ArcTrim"]),
                "dynamic_trim": float(s["DynamicTrim"]), "counter": int(s["AliveCounter"])}

    def encode_status(self, st: dict, counter: int) -> list:
        """The status dict of the simulator -> [WELD_STATUS, WELD_ACTUALS] python-can messages."""
        import can
        sig = {v: int(bool(st["bits"][k])) for k, v in _STATUS_BITS.items()}
        sig.update(ErrorNumber=int(st["error"]), CounterEcho=counter & 0xFF)
        act = {"Voltage": round(min(max(st["voltage"], 0.0), 655.35), 2),
               "Current": round(min(max(st["current"], 0.0), 6553.5), 1),
               "WFSActual": round(max(min(st["wfs"], 327.67), -327.68), 2), "CounterEcho": counter & 0xFF}
        return [can.Message(arbitration_id=self.sta_id, data=self.sta.encode(sig), is_extended_id=False),
                can.Message(arbitration_id=self.act_id, data=self.act.encode(act), is_extended_id=False)]

    def decode_status(self, data: bytes) -> dict:
        s = self.sta.decode(data, decode_choices=False)
        return {"bits": {k: bool(s[v]) for k, v in _STATUS_BITS.items()}, "error": int(s["ErrorNumber"]),
                "echo": int(s["CounterEcho"])}

    def decode_actuals(self, data: bytes) -> dict:
        s = self.act.decode(data, decode_choices=False)
        return {"voltage": float(s["Voltage"]), "current": float(s["Current"]), "wfs": float(s["WFSActual"]),
                "echo": int(s["CounterEcho"])}


class CanPowerSource(PowerSource):
    """`PowerSource` over CAN (python-can + cantools)."""

    COUNTER_MOD = 0x100

    def __init__(self, *, interface: str, channel: str, node: int = 1, dbc: str | Path = DEFAULT_DBC,
                 material=None, cycle_ms: float = 10.0, timeout_ms: float = 50.0, **bus_kwargs) -> None:
        super().__init__(f"can://{interface}/{channel}?node={node}", material, cycle_ms=cycle_ms,
                         timeout_ms=timeout_ms)
        import cantools
        try:
            db = cantools.database.load_file(str(dbc))
        except Exception as exc:
            raise ConfigError(f"{dbc}: cannot load the CAN database ({exc})") from None
        self.codec = CanCodec(db, node)
        self.interface, self.channel, self.node = interface, channel, node
        self.bus_kwargs = bus_kwargs
        self._bus = None
        self._notifier = None
        self._pending: tuple[int, asyncio.Future, dict] | None = None

    def where(self) -> str:
        return f"power source (CAN node {self.node}) on {self.interface} channel {self.channel}"

    async def _open(self) -> None:
        import can
        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, **self.bus_kwargs)
        except Exception as exc:
            raise LinkLost(f"{self.where()}: cannot open the bus ({exc})") from None
        self._notifier = can.Notifier(self._bus, [self._on_message], timeout=0.1,
                                      loop=asyncio.get_running_loop())

    async def _close(self) -> None:
        if self._notifier is not None:
            self._notifier.stop(timeout=0.5)
            self._notifier = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def _on_message(self, msg) -> None:
        p = self._pending
        if p is None or msg.is_extended_id:
            return
        counter, fut, got = p
        try:
            if msg.arbitration_id == self.codec.sta_id:
                d = self.codec.decode_status(bytes(msg.data))
                if d["echo"] == counter:
                    got["status"] = d
            elif msg.arbitration_id == self.codec.act_id:
                d = self.codec.decode_actuals(bytes(msg.data))
                if d["echo"] == counter:
                    got["actuals"] = d
            else:
                return
        except Exception:
            return  # a malformed frame from another node is not ours to judge
        if "status" in got and "actuals" in got and not fut.done():
            fut.set_result(got)

    async def _exchange(self, cmd: PowerCommand, counter: int) -> dict:
        import can
        if self._bus is None:
            raise LinkLost(f"{self.where()}: not connected")
        fut = asyncio.get_running_loop().create_future()
        self._pending = (counter & 0xFF, fut, {})
        try:
            data = self.codec.encode_command(cmd, counter)
        except Exception as exc:
            raise DeviceError(f"{self.where()}: cannot encode WELD_CMD ({exc})") from None
        try:
            self._bus.send(can.Message(arbitration_id=self.codec.cmd_id, data=data, is_extended_id=False))
        except can.CanError as exc:
            raise LinkLost(f"{self.where()}: send failed ({exc})") from None
        try:
            got = await fut
        finally:
            self._pending = None
        st, act = got["status"], got["actuals"]
        return {"echo": st["echo"], "bits": st["bits"], "error": st["error"], "voltage": act["voltage"],
                "current": act["current"], "wfs": act["wfs"]}

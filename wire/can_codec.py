"""The power source's CAN frames (config/power_source.dbc, cantools): one codec for the driver and the simulator.

`CanCodec` encodes and decodes WELD_CMD (0x200+n), WELD_STATUS (0x180+n) and WELD_ACTUALS
(0x280+n) of node n; `dbc_path` resolves cell.yaml's `can.dbc`.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

from core.errors import ConfigError


class CommandFields(Protocol):
    """What the codec reads from a power-source command (drivers.power.PowerCommand)."""

    @property
    def weld_start(self) -> bool: ...
    @property
    def robot_ready(self) -> bool: ...
    @property
    def error_reset(self) -> bool: ...
    @property
    def gas_test(self) -> bool: ...
    @property
    def wire_inch(self) -> bool: ...
    @property
    def wire_retract(self) -> bool: ...
    @property
    def mode(self) -> int: ...
    @property
    def job(self) -> int: ...
    @property
    def wfs_m_min(self) -> float: ...
    @property
    def arc_trim(self) -> float: ...
    @property
    def dynamic_trim(self) -> float: ...


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

    def __init__(self, db: Any, node: int = 1) -> None:
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

    def encode_command(self, cmd: CommandFields, counter: int) -> bytes:
        sig: dict[str, float] = {v: int(getattr(cmd, k)) for k, v in _CMD_BITS.items()}
        sig.update(Mode=cmd.mode, Job=cmd.job, WFS=round(cmd.wfs_m_min, 2), ArcTrim=round(cmd.arc_trim, 1),
                   DynamicTrim=round(cmd.dynamic_trim, 1), AliveCounter=counter & 0xFF)
        return bytes(self.cmd.encode(sig))

    def decode_command(self, data: bytes) -> dict[str, Any]:
        s = self.cmd.decode(data, decode_choices=False)
        return {"bits": {k: bool(s[v]) for k, v in _CMD_BITS.items()}, "mode": int(s["Mode"]),
                "job": int(s["Job"]), "wfs": float(s["WFS"]), "arc_trim": float(s["ArcTrim"]),
                "dynamic_trim": float(s["DynamicTrim"]), "counter": int(s["AliveCounter"])}

    def encode_status(self, st: Mapping[str, Any], counter: int) -> list[Any]:
        """The status dict of the simulator -> [WELD_STATUS, WELD_ACTUALS] python-can messages."""
        # lazy: python-can loads only when this path runs (start-up time)
        import can
        sig = {v: int(bool(st["bits"][k])) for k, v in _STATUS_BITS.items()}
        sig.update(ErrorNumber=int(st["error"]), CounterEcho=counter & 0xFF)
        act = {"Voltage": round(min(max(st["voltage"], 0.0), 655.35), 2),
               "Current": round(min(max(st["current"], 0.0), 6553.5), 1),
               "WFSActual": round(max(min(st["wfs"], 327.67), -327.68), 2), "CounterEcho": counter & 0xFF}
        return [can.Message(arbitration_id=self.sta_id, data=self.sta.encode(sig), is_extended_id=False),
                can.Message(arbitration_id=self.act_id, data=self.act.encode(act), is_extended_id=False)]

    def decode_status(self, data: bytes) -> dict[str, Any]:
        s = self.sta.decode(data, decode_choices=False)
        return {"bits": {k: bool(s[v]) for k, v in _STATUS_BITS.items()}, "error": int(s["ErrorNumber"]),
                "echo": int(s["CounterEcho"])}

    def decode_actuals(self, data: bytes) -> dict[str, Any]:
        s = self.act.decode(data, decode_choices=False)
        return {"voltage": float(s["Voltage"]), "current": float(s["Current"]), "wfs": float(s["WFSActual"]),
                "echo": int(s["CounterEcho"])}

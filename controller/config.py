"""Load YAML into validated frozen objects; every error names the file, the key path and the line."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from planner.errors import ConfigError
from planner.material import Material

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
M = TypeVar("M", bound=BaseModel)


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# --- cell.yaml -------------------------------------------------------------------------------


class CellInfo(_Frozen):
    name: str = "cell"
    platform: Literal["robot", "cnc"] = "robot"
    # Process time runs this many times faster than wall time in the simulators and the
    # controller (motion, gas flows, ignition, thermal). Link timing (heartbeats, the 10 ms
    # bus cycle, watchdogs, link-loss timeouts) is never scaled. Real hardware: 1.
    time_scale: float = Field(default=1.0, gt=0.0, le=1000.0)
    material: str = "inconel718-1.0mm"
    runs_dir: str = "runs"


class RobotDevice(_Frozen):
    url: str
    baud: int = Field(default=115200, gt=0)
    heartbeat_s: float = Field(default=1.0, gt=0.0)
    link_timeout_s: float = Field(default=3.0, gt=0.0)
    queue_slots: int = Field(default=64, gt=0, le=4096)


class CncDevice(_Frozen):
    url: str
    baud: int = Field(default=115200, gt=0)
    rx_buffer_bytes: int = Field(default=128, ge=32, le=4096)
    status_hz: float = Field(default=5.0, gt=0.0, le=5.0)


class CanSettings(_Frozen):
    interface: str = "udp_multicast"
    channel: str = "239.74.163.2"
    node: int = Field(default=1, ge=0, le=0x7F)
    dbc: str = "power_source.dbc"


class PowerSourceDevice(_Frozen):
    transport: Literal["modbus_tcp", "modbus_rtu", "can"] = "modbus_tcp"
    url: str = "tcp://127.0.0.1:5502"
    device_id: int = Field(default=1, ge=1, le=247)
    cycle_ms: float = Field(default=10.0, gt=0.0, le=1000.0)
    timeout_ms: float = Field(default=50.0, gt=0.0)
    can: CanSettings = CanSettings()
    # device properties a resume after a crash relies on (controller/arc_out.py): the start is
    # dropped after watchdog_ms (wall) without a new counter; the arc then burns on for
    # watchdog_burnback_s (process time; 0: the source goes idle at once, as the simulator does)
    watchdog_ms: float = Field(default=100.0, gt=0.0, le=10000.0)
    watchdog_burnback_s: float = Field(default=0.0, ge=0.0, le=10.0)


class CellIODevice(_Frozen):
    url: str = "tcp://127.0.0.1:5503"
    device_id: int = Field(default=1, ge=1, le=247)
    cycle_ms: float = Field(default=10.0, gt=0.0, le=1000.0)


class Devices(_Frozen):
    robot: RobotDevice
    cnc: CncDevice
    power_source: PowerSourceDevice
    cellio: CellIODevice


class Limits(_Frozen):
    travel_speed_mm_min: float = Field(default=3000.0, gt=0.0, le=60000.0)
    max_speed_mm_min: float = Field(default=6000.0, gt=0.0, le=60000.0)
    workspace_min_mm: tuple[float, float, float] = (-500.0, -500.0, -10.0)
    workspace_max_mm: tuple[float, float, float] = (500.0, 500.0, 500.0)
    clearance_mm: float = Field(default=10.0, ge=0.0, le=500.0)
    max_part_temperature_c: float = Field(default=400.0, gt=0.0, le=2000.0)


class Kinematics(_Frozen):
    table: Literal["AB", "AC"] = "AB"
    pivot_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis_a: tuple[float, float, float] = (1.0, 0.0, 0.0)
    axis_second: tuple[float, float, float] = (0.0, 1.0, 0.0)
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    a_limits_deg: tuple[float, float] = (-120.0, 120.0)
    second_limits_deg: tuple[float, float] = (-360.0, 360.0)


class ProbeSettings(_Frozen):
    fast_feed_mm_min: float = Field(default=300.0, gt=0.0)
    slow_feed_mm_min: float = Field(default=30.0, gt=0.0)
    travel_mm: float = Field(default=20.0, gt=0.0)
    backoff_mm: float = Field(default=2.0, gt=0.0)
    clearance_mm: float = Field(default=10.0, gt=0.0)
    samples: int = Field(default=3, ge=1, le=20)
    spread_tol_mm: float = Field(default=0.01, gt=0.0)
    retries: int = Field(default=2, ge=0, le=10)
    noise_mm: float = Field(default=0.002, ge=0.0, description="expected probe noise (1σ)")


class CellConfig(_Frozen):
    cell: CellInfo = CellInfo()
    devices: Devices
    limits: Limits = Limits()
    kinematics: Kinematics = Kinematics()
    probe: ProbeSettings = ProbeSettings()


# --- sim.yaml --------------------------------------------------------------------------------


class Workpiece(_Frozen):
    mesh: str | None = None
    size_mm: tuple[float, float, float] = (100.0, 100.0, 20.0)
    tilt_a_deg: float = Field(default=0.0, ge=-45.0, le=45.0)
    tilt_b_deg: float = Field(default=0.0, ge=-45.0, le=45.0)
    rotation_c_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)


class CncSim(_Frozen):
    workpiece: Workpiece = Workpiece()
    probe_noise_mm: float = Field(default=0.002, ge=0.0, le=1.0)


class ThermalSim(_Frozen):
    ambient_c: float = Field(default=20.0, ge=-40.0, le=60.0)
    heat_capacity_j_k: float = Field(default=2000.0, gt=0.0)
    cooling_time_constant_s: float = Field(default=120.0, gt=0.0)


class SimConfig(_Frozen):
    cnc: CncSim = CncSim()
    thermal: ThermalSim = ThermalSim()
    faults: str = ""


# --- loading ---------------------------------------------------------------------------------


def _node_at(node: yaml.Node | None, loc: tuple[Any, ...]) -> yaml.Node | None:
    """Walk a composed YAML node tree along a pydantic error location; deepest node found."""
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            nxt = None
            for k, v in node.value:
                if k.value == str(key):
                    nxt = v
                    break
            if nxt is None:
                return node
            node = nxt
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
        else:
            return node
    return node


def _key_node(node: yaml.Node | None, loc: tuple[Any, ...]) -> yaml.Node | None:
    """For an unknown key, the node of the key itself (so the line is the key's line)."""
    parent = _node_at(node, loc[:-1])
    if isinstance(parent, yaml.MappingNode):
        for k, _ in parent.value:
            if k.value == str(loc[-1]):
                return k
    return parent


def parse_model(text: str, model: type[M], source: str) -> M:
    """Validate YAML text against a model; errors name `source`, the key path and the line."""
    try:
        root = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{source}:{line}: not valid YAML ({getattr(exc, 'problem', exc)}); fix the syntax") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: line 1: expected a mapping of keys at the top level")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = tuple(err["loc"])
        path = ".".join(str(p) for p in loc) or "(top level)"
        etype = err["type"]
        if etype == "extra_forbidden":
            node = _key_node(root, loc)
            what = f"unknown key '{path}' (check its spelling and unit suffix)"
        elif etype == "missing":
            node = _node_at(root, loc[:-1])
            what = f"missing key '{path}'"
        else:
            node = _node_at(root, loc)
            what = f"key '{path}': {err['msg']}"
            if "input" in err and not isinstance(err["input"], (dict, list)):
                what += f" (got {err['input']!r})"
        line = f"line {node.start_mark.line + 1}: " if node is not None else ""
        more = f" (+{len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else ""
        raise ConfigError(f"{source}: {line}{what}{more}") from None


def load_model(path: str | Path, model: type[M]) -> M:
    """Read and validate a YAML file; a missing or unreadable file is a ConfigError too."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read ({exc.strerror or exc}); check the path") from None
    return parse_model(text, model, str(p))


def load_cell(path: str | Path | None = None) -> CellConfig:
    return load_model(path or CONFIG_DIR / "cell.yaml", CellConfig)


def load_sim(path: str | Path | None = None) -> SimConfig:
    return load_model(path or CONFIG_DIR / "sim.yaml", SimConfig)


def material_path(name_or_path: str) -> Path:
    """A material by name (config/materials/NAME.yaml) or by a path to a YAML file."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    cand = CONFIG_DIR / "materials" / f"{name_or_path}.yaml"
    if not cand.exists():
        known = ", ".join(sorted(x.stem for x in (CONFIG_DIR / "materials").glob("*.yaml")))
        raise ConfigError(f"material '{name_or_path}' not found; known materials: {known}")
    return cand


def load_material(name_or_path: str = "inconel718-1.0mm") -> Material:
    return load_model(material_path(name_or_path), Material)

"""Load YAML into validated frozen objects; every error names the file, the key path and the line."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Literal, TypeVar, get_args

import yaml
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, model_validator
from typing_extensions import Annotated

from core.config_cache import CONFIG_DIR as CONFIG_DIR  # re-exported: the light module (cell plan) has them
from core.config_cache import material_path as material_path
from core.errors import ConfigError
from core.material import Material
from core.process_control import ProcessControl as ProcessControl  # re-exported: cell.yaml's process_control
from core.tools import Machining, Tools

M = TypeVar("M", bound=BaseModel)

_NET_SCHEMES = ("socket", "tcp", "rfc2217", "udp")


def _device_url(v: str) -> str:
    """A device URL whose host and port parse (a port in 0..65535, 0: any free port), or a serial device path."""
    # stdlib, needed only on this path
    from urllib.parse import urlsplit

    if not v.strip():
        raise ValueError("empty device URL")
    if "://" not in v:
        return v  # a serial device path (/dev/ttyUSB0, COM3)
    try:
        u = urlsplit(v)
        port = u.port
    except ValueError as exc:
        raise ValueError(f"not a valid URL ({exc})") from None
    if u.scheme in _NET_SCHEMES:
        if not u.hostname:
            raise ValueError(f"{u.scheme}:// URL without a host (expected {u.scheme}://HOST:PORT)")
        if port is None:
            raise ValueError(f"{u.scheme}:// URL needs a port (expected {u.scheme}://HOST:PORT)")
    return v


DeviceUrl = Annotated[str, AfterValidator(_device_url)]


class _Frozen(BaseModel):
    # allow_inf_nan=False: `.inf`/`.nan` in a YAML file is an error naming the key, never a limit
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


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
    # Progress watchdog (docs/contract.md §6): process seconds a motion device may stand (no EXE, no
    # position change) with the arc on before it is a fault; null: from the job at build start,
    # the longest planned weld move's time x 2 + 1 s (docs/controller.md, Progress watchdog).
    progress_timeout_s: float | None = Field(default=None, gt=0.0, le=3600.0)


# The protocol / transport of each device kind: drivers/registry.py maps each name to its driver
# class (tests/drivers/test_registry.py keeps the two lists equal). A name not listed is an error that
# names the file, the key and the known names.
RobotProtocolName = Literal["rlp1"]
CncProtocolName = Literal["grbl"]
PowerTransportName = Literal["modbus_tcp", "modbus_rtu", "can"]
CellIOTransportName = Literal["modbus_tcp"]


def _one_of(what: str, names: tuple[str, ...]) -> Callable[[object], object]:
    """A before-validator naming the known values (pydantic's literal error only quotes them)."""
    def check(v: object) -> object:
        if isinstance(v, str) and v not in names:
            raise ValueError(f"unknown {what} {v!r}; known: {', '.join(names)}")
        return v
    return check


ROBOT_PROTOCOLS: tuple[str, ...] = get_args(RobotProtocolName)
CNC_PROTOCOLS: tuple[str, ...] = get_args(CncProtocolName)
POWER_TRANSPORTS: tuple[str, ...] = get_args(PowerTransportName)
CELLIO_TRANSPORTS: tuple[str, ...] = get_args(CellIOTransportName)
RobotProtocol = Annotated[RobotProtocolName, BeforeValidator(_one_of("robot protocol", ROBOT_PROTOCOLS))]
CncProtocol = Annotated[CncProtocolName, BeforeValidator(_one_of("CNC protocol", CNC_PROTOCOLS))]
PowerTransport = Annotated[PowerTransportName, BeforeValidator(_one_of("power-source transport", POWER_TRANSPORTS))]
CellIOTransport = Annotated[CellIOTransportName, BeforeValidator(_one_of("cell I/O transport", CELLIO_TRANSPORTS))]


class RobotDevice(_Frozen):
    protocol: RobotProtocol = "rlp1"      # rlp1: RLP/1 over a serial URL (docs/contract.md §5)
    url: DeviceUrl
    baud: int = Field(default=115200, gt=0)
    heartbeat_s: float = Field(default=1.0, gt=0.0)
    link_timeout_s: float = Field(default=3.0, gt=0.0)
    queue_slots: int = Field(default=64, gt=0, le=4096)


class CncDevice(_Frozen):
    protocol: CncProtocol = "grbl"        # grbl: grbl 1.1 / grblHAL line protocol (docs/contract.md §5)
    url: DeviceUrl
    baud: int = Field(default=115200, gt=0)
    rx_buffer_bytes: int = Field(default=128, ge=32, le=4096)
    status_hz: float = Field(default=5.0, gt=0.0, le=5.0)
    homing_timeout_s: float = Field(default=120.0, gt=0.0)   # $H is silent until done
    process_power: Literal["dynamic", "constant"] = "dynamic"   # M4 follows the speed; M3 (docs/laser-power.md)


class CanSettings(_Frozen):
    interface: str = "udp_multicast"
    channel: str = "239.74.163.2"
    node: int = Field(default=1, ge=0, le=0x7F)
    dbc: str = "power_source.dbc"
    # udp_multicast is kept on this host (TTL 0, loopback) unless this is true (wire/can_net.py)
    allow_network: bool = False


class PowerSourceDevice(_Frozen):
    transport: PowerTransport = "modbus_tcp"
    url: DeviceUrl = "tcp://127.0.0.1:5502"
    device_id: int = Field(default=1, ge=1, le=247)
    cycle_ms: float = Field(default=10.0, gt=0.0, le=1000.0)
    # link health (docs/contract.md §5): lost after this many consecutive cycles without a valid reply
    lost_after_cycles: int = Field(default=3, ge=1, le=100)
    timeout_ms: float | None = Field(default=None, gt=0.0)  # overrides it (a fixed reply timeout)
    can: CanSettings = CanSettings()
    # device properties a resume after a crash relies on (controller/runtime/arc_out.py): the start is
    # dropped after watchdog_ms (wall) without a new counter; the arc then burns on for
    # watchdog_burnback_s (process time; 0: the source goes idle at once, as the simulator does)
    watchdog_ms: float = Field(default=100.0, gt=0.0, le=10000.0)
    watchdog_burnback_s: float = Field(default=0.0, ge=0.0, le=10.0)


class CellIODevice(_Frozen):
    transport: CellIOTransport = "modbus_tcp"   # the remote I/O coupler (docs/contract.md §5)
    url: DeviceUrl = "tcp://127.0.0.1:5503"
    device_id: int = Field(default=1, ge=1, le=247)
    cycle_ms: float = Field(default=10.0, gt=0.0, le=1000.0)
    lost_after_cycles: int = Field(default=3, ge=1, le=100)


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
    # the job check before motion (controller/job/check.py): interpass limits must lie above the
    # ambient; a pass planned outside the material's envelope runs only where the cell allows it,
    # and then inside the power source's range
    ambient_c: float = Field(default=20.0, ge=-40.0, le=60.0)
    # a weld slower than this is a standing torch, not a bead (the arc would burn through)
    min_weld_speed_mm_min: float = Field(default=30.0, gt=0.0, le=6000.0)
    allow_outside_envelope: bool = False
    source_current_max_a: float = Field(default=500.0, gt=0.0, le=2000.0)
    source_wfs_max_m_min: float = Field(default=25.0, gt=0.0, le=50.0)


class Kinematics(_Frozen):
    table: Literal["AB", "AC"] = "AB"
    pivot_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis_a: tuple[float, float, float] = (1.0, 0.0, 0.0)
    axis_second: tuple[float, float, float] = (0.0, 1.0, 0.0)
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    a_limits_deg: tuple[float, float] = (-120.0, 120.0)
    second_limits_deg: tuple[float, float] = (-360.0, 360.0)
    tilt_limit_deg: float = Field(default=60.0, ge=0.0, le=120.0,
                                  description="largest tool-axis tilt from the part's vertical a 5-axis plan uses")
    chord_tolerance_mm: float = Field(
        default=0.02, gt=0.0, le=1.0,
        description="5-axis: the tool tip stays this close to the planned path between the points of a "
                    "machine-linear move; moves are split until it does (docs/kinematics.md)")


class Nozzle(_Frozen):
    """The torch/nozzle as a cone around the tool axis, for the plan-time collision check."""

    half_angle_deg: float = Field(default=15.0, gt=0.0, lt=80.0)
    length_mm: float = Field(default=60.0, gt=0.0)
    standoff_mm: float = Field(default=3.0, ge=0.0, description="cone tip above the bead centre line")


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


class OpcUaSettings(_Frozen):
    """The factory interface (docs/contract.md §8); off by default, loopback unless secured."""

    enabled: bool = False
    endpoint: str = "opc.tcp://127.0.0.1:4840/cell"
    allow_control: bool = False        # Pause/Resume/Abort methods exist only when true
    certificate: str | None = None     # server certificate (DER or PEM) and its key: with users,
    private_key: str | None = None     # the endpoint may leave the host and anonymous is refused
    users: dict[str, str] = Field(default_factory=dict)  # name -> "sha256:<hex of the password>"
    manufacturer: str = "cell-controller"
    model: str = "WAAM / laser deposition cell"
    serial_number: str = ""            # default: the cell's name


def _records_url(v: str | None) -> str | None:
    """`sqlite:///PATH` (a shop-wide file) or `postgresql://...` (the reference): docs/records.md."""
    if v is None:
        return None
    if v.startswith("sqlite:///") and len(v) > len("sqlite:///"):
        return v
    if v.startswith(("postgresql://", "postgres://")):
        return v
    raise ValueError(f"expected sqlite:///PATH or postgresql://USER@HOST:PORT/DB (got {v!r})")


RecordsUrl = Annotated[str | None, AfterValidator(_records_url)]


class RecordsSettings(_Frozen):
    """Traceability of every build and the shop's record store (docs/contract.md §9, docs/records.md).

    `wire_lot`, `gas`, `operator`: what is loaded on the cell and who runs it, unless the command
    (`--wire-lot`, `--gas`, `--operator`) or the TUI's start dialog gives them. `require_lot`: a
    build without a wire lot is refused before any motion. `url`: the shop's database each build's
    record is sent to (none: the run directories only)."""

    url: RecordsUrl = None
    require_lot: bool = False
    wire_lot: str | None = Field(default=None, min_length=1, max_length=200)
    gas: str | None = Field(default=None, min_length=1, max_length=200)
    operator: str | None = Field(default=None, min_length=1, max_length=200)
    connect_timeout_s: float = Field(default=5.0, gt=0.0, le=120.0)


class CellConfig(_Frozen):
    cell: CellInfo = CellInfo()
    devices: Devices
    limits: Limits = Limits()
    kinematics: Kinematics = Kinematics()
    nozzle: Nozzle = Nozzle()
    probe: ProbeSettings = ProbeSettings()
    opcua: OpcUaSettings = OpcUaSettings()
    process_control: ProcessControl = ProcessControl()
    records: RecordsSettings = RecordsSettings()
    tools: Tools = Tools()
    machining: Machining = Machining()

    @model_validator(mode="after")
    def _cutter_known(self) -> "CellConfig":
        name = self.machining.cutter
        if name is not None and name not in self.tools.cutters:
            raise ValueError(f"machining.cutter {name!r} is not in tools.cutters ({', '.join(self.tools.cutters)})")
        return self


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
    # unused since the deposit is the World's height map (sim.yaml `process:`); still accepted so older files load
    bead_width_mm: float = Field(default=4.0, gt=0.0)
    bead_depth_mm: float = Field(default=2.0, gt=0.0)


class ThermalSim(_Frozen):
    ambient_c: float = Field(default=20.0, ge=-40.0, le=60.0)
    # a weld slower than this is a standing torch, not a bead (the arc would burn through)
    min_weld_speed_mm_min: float = Field(default=30.0, gt=0.0, le=6000.0)
    heat_capacity_j_k: float = Field(default=2000.0, gt=0.0)
    cooling_time_constant_s: float = Field(default=120.0, gt=0.0)


class SimRegion(_Frozen):
    """A box of the substrate frame (xy, mm) where the world lays with its own hidden gains
    (they replace the global `height_gain` / `height_temp_coeff` there; the last region listed wins)."""

    box_mm: tuple[float, float, float, float]
    height_gain: float = Field(default=1.0, gt=0.0, le=3.0)
    height_temp_coeff: float = Field(default=0.0, ge=-0.01, le=0.01)

    @model_validator(mode="after")
    def _box(self) -> "SimRegion":
        x0, y0, x1, y1 = self.box_mm
        if not (x0 < x1 and y0 < y1):
            raise ValueError(f"box_mm: needs [x0, y0, x1, y1] with x0 < x1 and y0 < y1 (got {list(self.box_mm)})")
        return self

    def contains(self, x: float, y: float) -> bool:
        x0, y0, x1, y1 = self.box_mm
        return x0 <= x <= x1 and y0 <= y <= y1


class ProcessSim(_Frozen):
    """The simulated world's process physics (docs/contract.md §6b, docs/process-physics.md).

    Hidden truth: the controller never reads it. The bead's metal is the model's times
    `height_gain · (1 + height_temp_coeff · (T − 100 °C)⁺) · (1 + height_noise_pct/100 · N(0, 1))`,
    N drawn once per bead from the fault spec's seed.
    """

    height_gain: float = Field(default=1.0, gt=0.0, le=3.0, description="true bead height / model height")
    height_temp_coeff: float = Field(default=0.0, ge=-0.01, le=0.01,
                                     description="relative change of height per K of part temperature above 100 °C")
    height_noise_pct: float = Field(default=0.0, ge=0.0, le=50.0, description="bead-to-bead noise, 1σ (seeded)")
    stick_out_mm: float = Field(default=15.0, gt=0.0, le=60.0, description="nominal CTWD: the contact tip above the job's z")
    # the world's share of resistive heating at the nominal stick-out (0.3-0.5 is typical);
    # null: the material's (`melting.resistive_share`, or its fitted alpha/beta)
    resistive_share: float | None = Field(default=None, ge=0.05, le=0.8)
    cell_mm: float = Field(default=0.5, ge=0.1, le=0.5, description="height-map cell size")
    # the world's hidden disturbances along the path (docs/process-physics.md "Disturbances")
    regions: tuple[SimRegion, ...] = ()
    start_run_in_mm: float = Field(default=0.0, ge=0.0, le=100.0,
                                   description="a bead's first mm lay thinner (half the metal at its start), linearly to nominal")
    end_sag: float = Field(default=0.0, ge=0.0, le=0.9,
                           description="share of the metal of a bead's last width that runs off an open end")


class SimConfig(_Frozen):
    cnc: CncSim = CncSim()
    thermal: ThermalSim = ThermalSim()
    process: ProcessSim = ProcessSim()
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
                key: yaml.Node = k
                return key
    return parent


def _duplicate_key(root: yaml.Node | None) -> yaml.ScalarNode | None:
    """The second occurrence of a key repeated within one mapping, if any (iterative walk)."""
    stack = [root] if root is not None else []
    while stack:
        node = stack.pop()
        if isinstance(node, yaml.MappingNode):
            seen: set[str] = set()
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode):
                    if k.value in seen:
                        return k
                    seen.add(k.value)
                stack.append(v)
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
    return None


def parse_model(text: str, model: type[M], source: str) -> M:
    """Validate YAML text against a model; errors name `source`, the key path and the line."""
    try:
        root = yaml.compose(text)
        data = yaml.safe_load(text)
    except RecursionError:
        raise ConfigError(f"{source}: nested too deeply to read; give a flat YAML file") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{source}:{line}: not valid YAML ({getattr(exc, 'problem', exc)}); fix the syntax") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: line 1: expected a mapping of keys at the top level")
    dup = _duplicate_key(root)
    if dup is not None:
        raise ConfigError(f"{source}: line {dup.start_mark.line + 1}: key '{dup.value}' is given twice in the same "
                          "mapping (the last one would silently win); keep one")
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
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read ({exc.strerror or exc}); check the path") from None
    return parse_model(text, model, str(p))


def load_cell(path: str | Path | None = None) -> CellConfig:
    return load_model(path or CONFIG_DIR / "cell.yaml", CellConfig)


def load_sim(path: str | Path | None = None) -> SimConfig:
    return load_model(path or CONFIG_DIR / "sim.yaml", SimConfig)


def load_material(name_or_path: str = "inconel718-1.0mm") -> Material:
    return load_model(material_path(name_or_path), Material)

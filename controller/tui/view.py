"""What the TUI shows: view dataclasses (a frozen picture of the cell) and their summarisers."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from planner.job import Job, Pass
from controller.api import Snapshot

HISTORY_LEN = 300          # samples kept for the live plots (30 s at 10 Hz)
SAMPLE_PERIOD_S = 0.1      # history sampling period (wall seconds)
ROLES = ("perimeter", "infill", "gap")
# Where the substrate may be probed on the CNC's link outside the facade (as `cell demo` does on a
# robot cell): the cell is connected and no build runs.
PROBE_STATES = ("idle", "ready", "aligned", "complete", "aborted")
# How the drivers and the interlocks name each device in their messages.
DEVICE_WORDS = {"robot": ("robot",), "cnc": ("cnc", "CNC"), "power_source": ("power_source", "power source"),
                "cellio": ("cellio", "cell I/O")}


@dataclass(frozen=True)
class Sample:
    """Live process values at one moment (for the Build screen's plots)."""

    t: float
    current_a: float | None
    voltage_v: float | None
    wfs_m_min: float | None
    temperature_c: float | None


@dataclass(frozen=True)
class RoleParams:
    """Process parameters of one bead role in the job (ranges over its passes)."""

    role: str
    passes: int
    width_mm: float
    current_a: tuple[float, float]
    speed_mm_min: tuple[float, float]
    wfs_m_min: tuple[float, float]


@dataclass(frozen=True)
class JobInfo:
    """The open job as the Job screen shows it."""

    name: str
    source: str
    layers: int
    passes: int
    bead: dict[str, Any]
    summary: dict[str, Any]
    roles: tuple[RoleParams, ...]
    # per layer: tuple of (role, ((x, y), ...)) for the terminal preview
    layer_paths: tuple[tuple[tuple[str, tuple[tuple[float, float], ...]], ...], ...] = ()


@dataclass(frozen=True)
class PlanStatus:
    state: str = "none"            # none, loaded (STL chosen, not planned), planning, done, error
    file: str | None = None
    width_mm: float | None = None
    done: int = 0                  # layers sliced so far
    total: int = 0
    error: str | None = None


@dataclass(frozen=True)
class DeviceInfo:
    device: str
    url: str
    connected: bool
    frames_tx: int = 0
    frames_rx: int = 0
    errors: int = 0
    queue_free: int | None = None
    last_error: str | None = None


@dataclass(frozen=True)
class LogRow:
    id: int
    t: float
    kind: str                      # transition, alarm, info, ui
    state: str | None
    message: str
    layer: int | None = None
    pass_: int | None = None


@dataclass(frozen=True)
class View:
    """Everything the TUI draws, at one moment. Plain immutable values."""

    snap: Snapshot
    seq: int = 0                   # snapshots received so far (the UI shows the latest only)
    history: tuple[Sample, ...] = ()
    plan: PlanStatus = PlanStatus()
    job: JobInfo | None = None
    alignment: dict[str, Any] | None = None  # planes, level_a_deg, level_b_deg, face_angle_deg, transform
    alignment_applied: bool = False  # the job open now is the aligned one: `y` is spent
    probe_plan: tuple[tuple[str, tuple[float, float, float]], ...] = ()
    probed: tuple[tuple[str, tuple[float, float, float], float], ...] = ()  # (name, xyz, spread) as they arrive
    can_probe: bool = False        # a CNC with the touch probe is there (CNC platform, or --sim)
    platform: str = "robot"
    devices: tuple[DeviceInfo, ...] = ()
    sim: bool = False
    connect_error: str | None = None
    busy: str | None = None        # a command in progress (planning, aligning, connecting)

    def allowed(self, command: str) -> bool:
        """Whether a command may be sent now (the controller's allowed_commands, plus UI steps)."""
        if command == "plan":  # planning needs no cell; the job opens when the devices answer
            return self._may_plan()
        if command == "apply_alignment":
            return self._may_apply_alignment()
        if command == "connect":  # (re)connect: at start, or after a link loss latched a fault
            return self.snap.state in ("disconnected", "fault") and self.busy is None
        if command == "open":
            return self.busy is None and self._job_may_open()
        if command == "run_alignment":
            return self._may_probe()
        return command in self.snap.allowed_commands

    def _job_may_open(self) -> bool:
        """No cell yet (the job opens when the devices answer), or the controller takes a job now."""
        return self.snap.state == "disconnected" or "open_job" in self.snap.allowed_commands

    def _may_plan(self) -> bool:
        file = self.plan.file
        return self.plan.state in ("loaded", "error", "done") and file is not None \
            and file.lower().endswith((".stl", ".obj", ".3mf")) and self.busy is None and self._job_may_open()

    def _may_apply_alignment(self) -> bool:
        return (self.alignment is not None and self.job is not None and not self.alignment_applied
                and "open_job" in self.snap.allowed_commands)

    def _may_probe(self) -> bool:
        if self.busy is not None or not self.can_probe:
            return False
        return "run_alignment" in self.snap.allowed_commands or self.snap.state in PROBE_STATES


# -- job helpers (pure) --------------------------------------------------------------------------


def job_info(job: Job, name: str | None = None) -> JobInfo:
    """The summary, per-role parameters and 2-D layer paths of a typed job (planner.job)."""
    per: dict[str, list[Pass]] = {}
    layer_paths = []
    for la in job.layers:
        paths = []
        for p in la.passes:
            per.setdefault(p.role, []).append(p)
            pts = tuple((round(x, 3), round(y, 3)) for x, y in p.points[:, :2].tolist())
            paths.append((p.role, pts))
        layer_paths.append(tuple(paths))

    def rng(ps: list[Pass], key: str) -> tuple[float, float]:
        vals = [float(getattr(p, key)) for p in ps]
        return (min(vals), max(vals)) if vals else (math.nan, math.nan)

    roles = tuple(RoleParams(role=r, passes=len(ps), width_mm=rng(ps, "width_mm")[1],
                             current_a=rng(ps, "current_a"), speed_mm_min=rng(ps, "speed_mm_min"),
                             wfs_m_min=rng(ps, "wfs_m_min"))
                  for r, ps in sorted(per.items(), key=lambda kv: (ROLES + (kv[0],)).index(kv[0])))
    if name is None:
        name = Path(job.source.file or "job").stem
    return JobInfo(name=name, source=job.source.file, layers=len(job.layers),
                   passes=sum(len(la.passes) for la in job.layers), bead=dataclasses.asdict(job.bead),
                   summary=dict(job.summary), roles=roles, layer_paths=tuple(layer_paths))


def alignment_dict(result: Any) -> dict[str, Any] | None:
    """An alignment result (AlignResult.to_json(), a dict, a dataclass) as plain values for the view.

    Each plane gets its probed points and their residuals (signed distance along the normal)
    when the result carries them.
    """
    if result is None:
        return None
    d: dict[str, Any] = _plain(_fields(result))
    raw_pts = d.get("points")
    pts: dict[str, Any] = raw_pts if isinstance(raw_pts, dict) else {}
    planes = d.get("planes") or []
    for pl in planes if isinstance(planes, list) else []:
        if isinstance(pl, dict):
            _add_residuals(pl, pts)
    return d


def _fields(result: Any) -> dict[str, Any]:
    """The fields of a result given as a dict, an object with to_json(), a dataclass or any object."""
    if isinstance(result, dict):
        return dict(result)
    if hasattr(result, "to_json"):
        return dict(result.to_json())
    if hasattr(result, "__dataclass_fields__"):
        return {k: getattr(result, k) for k in result.__dataclass_fields__}
    return {k: v for k, v in vars(result).items() if not k.startswith("_")}


def _add_residuals(pl: dict[str, Any], pts: dict[str, Any]) -> None:
    """Give a plane its probed points (from the result's `points`) and their signed residuals."""
    name = pl.get("name")
    if "points" not in pl and name in pts:
        pl["points"] = pts[name]
    n, c = pl.get("normal"), pl.get("point")
    if "residuals" not in pl and pl.get("points") and n and c:
        pl["residuals"] = [sum((p[i] - c[i]) * n[i] for i in range(3)) for p in pl["points"]]


def _plain(v: Any) -> Any:
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if hasattr(v, "__dataclass_fields__"):
        out = {k: _plain(getattr(v, k)) for k in v.__dataclass_fields__}
        return out
    return v

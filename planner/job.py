"""The job file `cell-job/1`: frozen dataclasses, canonical JSON bytes, and a validating reader."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.errors import InputError

SCHEMA = "cell-job/1"
ROLES = ("perimeter", "infill", "gap")
FRAMES = ("substrate", "cad")


@dataclass(frozen=True)
class Source:
    file: str
    sha256: str
    units: str


@dataclass(frozen=True)
class BeadInfo:
    width_mm: float
    height_mm: float
    step_over_mm: float
    model: str


@dataclass(frozen=True, eq=False)
class Pass:
    """One continuous arc-on bead: the arc starts at the first point and ends at the last."""

    role: str
    width_mm: float
    current_a: float
    speed_mm_min: float
    wfs_m_min: float
    points: np.ndarray  # (n, 3) mm
    normals: np.ndarray | None = None  # (n, 3) unit facet normals (perimeters), optional
    axes: np.ndarray | None = None     # (n, 3) unit tool axes in the part frame (5-axis plans)
    inside_envelope: bool = True       # False only under --allow-outside (written only then)

    @property
    def length_mm(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


@dataclass(frozen=True)
class Interpass:
    max_temperature_c: float
    dwell_s: float


@dataclass(frozen=True, eq=False)
class Layer:
    index: int
    z_mm: float
    height_mm: float
    passes: tuple[Pass, ...]
    interpass: Interpass | None = None
    extra: dict[str, Any] = field(default_factory=dict)  # area_mm2, coverage, ... (informative)


@dataclass(frozen=True, eq=False)
class Job:
    source: Source
    material: dict[str, Any]
    bead: BeadInfo
    layers: tuple[Layer, ...]
    summary: dict[str, Any]
    schema: str = SCHEMA
    frame: str = "substrate"  # substrate: lowest point on z = 0; cad: the CAD coordinates kept


def _num(x: float, nd: int) -> float:
    v = round(float(x), nd)
    return 0.0 if v == 0 else v  # no "-0.0" in the file


def _arr(a: np.ndarray, nd: int) -> list[Any]:
    r = np.round(np.asarray(a, dtype=np.float64), nd) + 0.0
    out: list[Any] = r.tolist()
    return out


def job_to_dict(job: Job) -> dict[str, Any]:
    layers = []
    for L in job.layers:
        passes = []
        for p in L.passes:
            d = {"role": p.role, "width_mm": _num(p.width_mm, 3), "current_a": _num(p.current_a, 2),
                 "speed_mm_min": _num(p.speed_mm_min, 1), "wfs_m_min": _num(p.wfs_m_min, 3),
                 "points": _arr(p.points, 3)}
            if p.normals is not None:
                d["normals"] = _arr(p.normals, 4)
            if p.axes is not None:
                d["axes"] = _arr(p.axes, 5)
            if not p.inside_envelope:
                d["inside_envelope"] = False
            passes.append(d)
        ld: dict[str, Any] = {"index": L.index, "z_mm": _num(L.z_mm, 4), "height_mm": _num(L.height_mm, 4),
                              "passes": passes}
        if L.interpass is not None:
            ld["interpass"] = {"max_temperature_c": L.interpass.max_temperature_c, "dwell_s": L.interpass.dwell_s}
        ld.update(L.extra)
        layers.append(ld)
    return {"schema": job.schema,
            "source": {"file": job.source.file, "sha256": job.source.sha256, "units": job.source.units},
            "material": job.material,
            "bead": {"width_mm": _num(job.bead.width_mm, 4), "height_mm": _num(job.bead.height_mm, 4),
                     "step_over_mm": _num(job.bead.step_over_mm, 4), "model": job.bead.model},
            "layers": layers, "summary": job.summary, "frame": job.frame}


def job_to_json(job: Job) -> bytes:
    """Canonical bytes: sorted keys, compact separators, fixed rounding: same job, same bytes."""
    return (json.dumps(job_to_dict(job), sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n").encode()


# ---- reading -----------------------------------------------------------------------------------

def _get(d: Any, key: str, where: str) -> Any:
    if not isinstance(d, dict):
        raise InputError(f"job file: {where or 'top level'} must be an object")
    if key not in d:
        raise InputError(f"job file: missing field {where + '.' if where else ''}{key}")
    return d[key]


def _number(d: dict[str, Any], key: str, where: str, positive: bool = False) -> float:
    v = _get(d, key, where)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"job file: {where}.{key} must be a number, got {v!r}")
    if positive and v <= 0:
        raise InputError(f"job file: {where}.{key} must be > 0, got {v!r}")
    return float(v)


def _points(v: Any, where: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"job file: {where} must be a list of [x, y, z] numbers") from None
    if a.ndim != 2 or a.shape[1] != 3 or not np.all(np.isfinite(a)):
        raise InputError(f"job file: {where} must be a list of [x, y, z] numbers")
    return a


def _axes(p: dict[str, Any], pw: str, n: int) -> np.ndarray | None:
    if "axes" not in p:
        return None
    ax = _points(p["axes"], f"{pw}.axes")
    if len(ax) != n:
        raise InputError(f"job file: {pw}.axes has {len(ax)} rows for {n} points")
    if not np.allclose(np.linalg.norm(ax, axis=1), 1.0, atol=1e-3):
        raise InputError(f"job file: {pw}.axes must be unit vectors [i, j, k]")
    return ax


def _pass(p: Any, pw: str) -> Pass:
    role = _get(p, "role", pw)
    if role not in ROLES:
        raise InputError(f"job file: {pw}.role is {role!r}, expected one of {', '.join(ROLES)}")
    pts = _points(_get(p, "points", pw), f"{pw}.points")
    if len(pts) < 2:
        raise InputError(f"job file: {pw}.points needs at least 2 points")
    normals = None
    if "normals" in p:
        normals = _points(p["normals"], f"{pw}.normals")
        if len(normals) != len(pts):
            raise InputError(f"job file: {pw}.normals has {len(normals)} rows for {len(pts)} points")
    axes = _axes(p, pw, len(pts))
    inside = p.get("inside_envelope", True)
    if not isinstance(inside, bool):
        raise InputError(f"job file: {pw}.inside_envelope must be true or false")
    return Pass(role, _number(p, "width_mm", pw, True), _number(p, "current_a", pw, True),
                _number(p, "speed_mm_min", pw, True), _number(p, "wfs_m_min", pw, True),
                pts, normals, axes, inside)


def load_job(d: Any) -> Job:
    """Validate a parsed `cell-job/1` object; a bad field raises InputError naming it."""
    schema = _get(d, "schema", "")
    if schema != SCHEMA:
        raise InputError(f"job file: schema is {schema!r}, expected {SCHEMA!r}")
    src = _get(d, "source", "")
    source = Source(str(_get(src, "file", "source")), str(_get(src, "sha256", "source")),
                    str(_get(src, "units", "source")))
    material = _get(d, "material", "")
    if not isinstance(material, dict):
        raise InputError("job file: material must be an object")
    b = _get(d, "bead", "")
    bead = BeadInfo(_number(b, "width_mm", "bead", True), _number(b, "height_mm", "bead", True),
                    _number(b, "step_over_mm", "bead", True), str(_get(b, "model", "bead")))
    raw_layers = _get(d, "layers", "")
    if not isinstance(raw_layers, list):
        raise InputError("job file: layers must be a list")
    layers = []
    for i, L in enumerate(raw_layers):
        w = f"layers[{i}]"
        idx = _get(L, "index", w)
        if isinstance(idx, bool) or not isinstance(idx, int):
            raise InputError(f"job file: {w}.index must be an integer")
        raw_passes = _get(L, "passes", w)
        if not isinstance(raw_passes, list):
            raise InputError(f"job file: {w}.passes must be a list")
        passes = [_pass(p, f"{w}.passes[{j}]") for j, p in enumerate(raw_passes)]
        ip = None
        if "interpass" in L:
            ip = Interpass(_number(L["interpass"], "max_temperature_c", f"{w}.interpass"),
                           _number(L["interpass"], "dwell_s", f"{w}.interpass"))
        extra = {k: v for k, v in L.items() if k not in ("index", "z_mm", "height_mm", "passes", "interpass")}
        layers.append(Layer(idx, _number(L, "z_mm", w), _number(L, "height_mm", w, True), tuple(passes), ip, extra))
    summary = d.get("summary", {})
    if not isinstance(summary, dict):
        raise InputError("job file: summary must be an object")
    frame = d.get("frame", "substrate")
    if frame not in FRAMES:
        raise InputError(f"job file: frame is {frame!r}, expected one of {', '.join(FRAMES)}")
    return Job(source, material, bead, tuple(layers), summary, frame=frame)


def loads_job(data: bytes | str) -> Job:
    """Parse and validate job-file text; malformed JSON is an InputError too."""
    try:
        d = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"job file: not valid JSON ({exc})") from None
    return load_job(d)

"""The job file (`cell-job/1`, `cell-job/2`): frozen dataclasses, canonical JSON bytes, and a
validating reader.

`cell-job/2` lets a pass carry `speed_mm_min` and `wfs_m_min` as arrays of one value per segment
(segment i runs from point i to i + 1) instead of one number (docs/along-the-path.md). A job with
any array is written as `cell-job/2`; a `cell-job/1` file reads as before; any other schema is
refused by name. The typed `Pass` keeps the scalars (for an array: its length-weighted mean, what
a summary or a record's "planned speed" shows) and the arrays beside them (`seg_speed_mm_min`,
`seg_wfs_m_min`); a consumer that moves the torch or feeds the wire asks `speeds()` /
`wire_feeds()`, which give one value per segment whichever form the file had.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from core.errors import InputError

SCHEMA = "cell-job/1"
SCHEMA_V2 = "cell-job/2"      # a pass may carry per-segment speed / wire feed arrays
SCHEMAS = (SCHEMA, SCHEMA_V2)
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
    seg_speed_mm_min: np.ndarray | None = None  # (n - 1,) travel speed per segment (cell-job/2), else None
    seg_wfs_m_min: np.ndarray | None = None     # (n - 1,) wire feed per segment (cell-job/2), else None

    @property
    def length_mm(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    @property
    def per_segment(self) -> bool:
        """True when the pass carries per-segment speed or wire feed (cell-job/2)."""
        return self.seg_speed_mm_min is not None or self.seg_wfs_m_min is not None

    def segment_lengths(self) -> np.ndarray:
        """(n - 1,) mm: the length of every segment."""
        out: np.ndarray = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return out

    def speeds(self) -> np.ndarray:
        """(n - 1,) mm/min: the travel speed of every segment (the pass's one speed when it has no array)."""
        if self.seg_speed_mm_min is not None:
            return self.seg_speed_mm_min
        return np.full(len(self.points) - 1, self.speed_mm_min)

    def wire_feeds(self) -> np.ndarray:
        """(n - 1,) m/min: the wire feed of every segment (the pass's one wire feed when it has no array)."""
        if self.seg_wfs_m_min is not None:
            return self.seg_wfs_m_min
        return np.full(len(self.points) - 1, self.wfs_m_min)

    @property
    def arc_time_s(self) -> float:
        """Seconds of arc at the planned speeds (each segment at its own)."""
        return float(np.sum(self.segment_lengths() / self.speeds()) * 60.0)

    def with_process(self, speeds: np.ndarray | None, wfs: np.ndarray | None) -> "Pass":
        """A copy with per-segment speeds and/or wire feeds (None: the pass's own kept); the scalars
        become their length-weighted means. Arrays whose values are all one are stored as that number."""
        sp = _seg(speeds, self.seg_speed_mm_min, len(self.points))
        wf = _seg(wfs, self.seg_wfs_m_min, len(self.points))
        lens = self.segment_lengths()
        return replace(self, speed_mm_min=self.speed_mm_min if sp is None else weighted_mean(sp, lens),
                       wfs_m_min=self.wfs_m_min if wf is None else weighted_mean(wf, lens),
                       seg_speed_mm_min=sp, seg_wfs_m_min=wf)

    def scaled(self, speed_factor: float = 1.0, wfs_factor: float = 1.0) -> "Pass":
        """A copy with every speed (scalar and per segment) times `speed_factor`, every wire feed times `wfs_factor`."""
        sp = None if self.seg_speed_mm_min is None else self.seg_speed_mm_min * speed_factor
        wf = None if self.seg_wfs_m_min is None else self.seg_wfs_m_min * wfs_factor
        return replace(self, speed_mm_min=self.speed_mm_min * speed_factor, wfs_m_min=self.wfs_m_min * wfs_factor,
                       seg_speed_mm_min=sp, seg_wfs_m_min=wf)


def weighted_mean(values: np.ndarray, lengths: np.ndarray) -> float:
    """The length-weighted mean of per-segment values (the plain mean when the pass has no length)."""
    total = float(np.sum(lengths))
    if total <= 0.0:
        return float(np.mean(values))
    return float(np.sum(values * lengths) / total)


def _seg(new: np.ndarray | None, old: np.ndarray | None, n_points: int) -> np.ndarray | None:
    if new is None:
        return old
    a = np.asarray(new, dtype=np.float64)
    if a.shape != (n_points - 1,):
        raise ValueError(f"{a.shape[0] if a.ndim else 0} per-segment values for {n_points - 1} segments")
    return a.copy()


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


def schema_of(job: Job) -> str:
    """`cell-job/2` when any pass carries a per-segment array, else the job's own schema."""
    if any(p.per_segment for L in job.layers for p in L.passes):
        return SCHEMA_V2
    return job.schema


def job_to_dict(job: Job) -> dict[str, Any]:
    return _job_dict(job, _arr)


def _job_dict(job: Job, arr: Callable[[np.ndarray, int], Any]) -> dict[str, Any]:
    layers = []
    for L in job.layers:
        passes = []
        for p in L.passes:
            speed: Any = _num(p.speed_mm_min, 1) if p.seg_speed_mm_min is None else arr(p.seg_speed_mm_min, 1)
            wfs: Any = _num(p.wfs_m_min, 3) if p.seg_wfs_m_min is None else arr(p.seg_wfs_m_min, 3)
            d = {"role": p.role, "width_mm": _num(p.width_mm, 3), "current_a": _num(p.current_a, 2),
                 "speed_mm_min": speed, "wfs_m_min": wfs, "points": arr(p.points, 3)}
            if p.normals is not None:
                d["normals"] = arr(p.normals, 4)
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
    return {"schema": schema_of(job),
            "source": {"file": job.source.file, "sha256": job.source.sha256, "units": job.source.units},
            "material": job.material,
            "bead": {"width_mm": _num(job.bead.width_mm, 4), "height_mm": _num(job.bead.height_mm, 4),
                     "step_over_mm": _num(job.bead.step_over_mm, 4), "model": job.bead.model},
            "layers": layers, "summary": job.summary, "frame": job.frame}


def job_to_json(job: Job) -> bytes:
    """Canonical bytes: sorted keys, compact separators, fixed rounding: same job, same bytes."""
    if sum(len(p.points) for L in job.layers for p in L.passes) >= BULK_POINTS:
        out = _bulk_json(job)
        if out is not None:
            return out
    return _dumps(job_to_dict(job))


def _dumps(d: dict[str, Any]) -> bytes:
    return (json.dumps(d, sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n").encode()


BULK_POINTS = 20_000   # points in a job from which its arrays are written by orjson (its import: 18 ms)
_HELD = re.compile(r'"\\u0001(\d+)"')


def _bulk_json(job: Job) -> bytes | None:
    """The same bytes as `_dumps(job_to_dict(job))`, the numeric arrays written straight from numpy
    by orjson (docs/plan-speed.md): each array's place in the document is held by a string json
    writes as "\\u0001<k>" (a control character: no text of the job is written so), then the
    array's text put there. orjson and Python write a float the same way (its shortest repr) but
    for magnitudes under 1e-4 or from 1e16 on, which rounding to at most 4 decimals and sizes
    under 1e15 rule out (an array that is not is written by json). None without orjson."""
    try:
        import orjson  # lazy: only large jobs use it
    except ImportError:   # an environment installed before it was pinned: json writes the same bytes
        return None
    held: list[bytes] = []

    def hold(a: np.ndarray, nd: int) -> Any:
        r = np.round(np.asarray(a, dtype=np.float64), nd) + 0.0
        if not bool(np.all(np.abs(r) < 1e15)):   # too large or not finite: as json writes (or refuses) it
            return _arr(a, nd)
        held.append(orjson.dumps(r, option=orjson.OPT_SERIALIZE_NUMPY))
        return f"\x01{len(held) - 1}"

    text = _dumps(_job_dict(job, hold)).decode()
    parts = _HELD.split(text)   # text, k, text, k, ..., text
    ks = [int(k) for k in parts[1::2]]
    if sorted(ks) != list(range(len(held))):   # each held array in its one place (keys are sorted)
        return None
    out = [parts[0].encode()]
    for i, k in enumerate(ks):
        out += [held[k], parts[2 * i + 2].encode()]
    return b"".join(out)


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


def _per_segment(p: dict[str, Any], key: str, pw: str, n: int, schema: str) -> tuple[float, np.ndarray | None]:
    """A pass's speed or wire feed: one number, or (cell-job/2) one number > 0 per segment."""
    v = _get(p, key, pw)
    if not isinstance(v, list):
        return _number(p, key, pw, True), None
    if schema != SCHEMA_V2:
        raise InputError(f"job file: {pw}.{key} is a list (per-segment values): that is {SCHEMA_V2}, "
                         f"but the file says schema {schema!r}; set \"schema\": \"{SCHEMA_V2}\"")
    if len(v) != n - 1:
        raise InputError(f"job file: {pw}.{key} has {len(v)} values for {n - 1} segments ({n} points); "
                         "give one per segment (segment i runs from point i to i + 1)")
    for k, x in enumerate(v):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x <= 0:
            raise InputError(f"job file: {pw}.{key}[{k}] must be a number > 0, got {x!r}")
    a = np.asarray(v, dtype=np.float64)
    return float(np.mean(a)), a   # the caller weighs the mean by the segments' lengths


def _pass(p: Any, pw: str, schema: str = SCHEMA) -> Pass:
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
    lens = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    speed, seg_speed = _per_segment(p, "speed_mm_min", pw, len(pts), schema)
    wfs, seg_wfs = _per_segment(p, "wfs_m_min", pw, len(pts), schema)
    if seg_speed is not None:
        speed = weighted_mean(seg_speed, lens)
    if seg_wfs is not None:
        wfs = weighted_mean(seg_wfs, lens)
    return Pass(role, _number(p, "width_mm", pw, True), _number(p, "current_a", pw, True), speed, wfs,
                pts, normals, axes, inside, seg_speed, seg_wfs)


def load_job(d: Any) -> Job:
    """Validate a parsed `cell-job/1` or `cell-job/2` object; a bad field raises InputError naming it."""
    schema = _get(d, "schema", "")
    if schema not in SCHEMAS:
        raise InputError(f"job file: schema is {schema!r}, which this controller does not know "
                         f"(it reads {' and '.join(repr(s) for s in SCHEMAS)}); plan the job again or use a newer controller")
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
        passes = [_pass(p, f"{w}.passes[{j}]", schema) for j, p in enumerate(raw_passes)]
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
    return Job(source, material, bead, tuple(layers), summary, schema=schema, frame=frame)


def loads_job(data: bytes | str) -> Job:
    """Parse and validate job-file text; malformed JSON is an InputError too."""
    try:
        d = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"job file: not valid JSON ({exc})") from None
    return load_job(d)

"""The job checked against the cell before any device is touched (DESIGN.md §6, issue 14).

Pure: the job (parsed JSON), the cell config and the material in, a list of violations out.
Every point of every pass must lie inside the workspace after the job's alignment transform,
every speed in (0, max_speed], every current and wire feed inside the material's envelope (or,
for a pass planned with `inside_envelope: false` on a cell that allows it, inside the power
source's range), every interpass limit inside (ambient, max part temperature), and the pass
and point counts bounded so a hand-edited job can never exhaust memory or time.
"""
from __future__ import annotations

import math
from functools import lru_cache
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.job.read import JobJSON
from core.config import CellConfig
from core.errors import CellError, InputError
from core.material import Material

MAX_PASSES = 200_000          # a 1 m³ part at 7 mm beads has ~60 000 passes
MAX_POINTS = 5_000_000        # points over the whole job (the planner's own: a few 100 000)
MAX_POINTS_PER_PASS = 1_000_000


@dataclass(frozen=True)
class Violation:
    """One thing of the job the cell cannot do."""

    layer: int | None
    pass_: int | None
    point: int | None
    what: str

    def where(self) -> str:
        parts = []
        if self.layer is not None:
            parts.append(f"layer {self.layer}")
        if self.pass_ is not None:
            parts.append(f"pass {self.pass_}")
        if self.point is not None:
            parts.append(f"point {self.point}")
        return ", ".join(parts)


class JobCheckError(InputError):
    """The job asks for something outside what the cell can do; nothing was sent to a device."""

    def __init__(self, source: str, violations: list[Violation]) -> None:
        self.violations = violations
        first = violations[0]
        more = f" ({len(violations)} violations in all; fix the job and plan it again)" if len(violations) > 1 \
            else " (fix the job and plan it again)"
        where = f"{first.where()}: " if first.where() else ""
        super().__init__(f"{source}: job refused before any motion: {where}{first.what}{more}")


def _transform(job: JobJSON) -> np.ndarray | None:
    al = job.get("alignment")
    if not isinstance(al, dict) or al.get("transform") is None:
        return None
    try:
        t = np.asarray(al["transform"], dtype=float)
    except (TypeError, ValueError):
        raise InputError("job file: alignment.transform must be a 4x4 matrix of numbers") from None
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise InputError("job file: alignment.transform must be a 4x4 matrix of finite numbers")
    return t


def _points(p: dict[str, Any], li: int, pi: int) -> np.ndarray:
    try:
        pts = np.asarray(p.get("points"), dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"job file: layers[{li}].passes[{pi}].points must be [x, y, z] numbers") from None
    if pts.ndim != 2 or pts.shape[1] < 3 or pts.shape[0] < 2:
        raise InputError(f"job file: layers[{li}].passes[{pi}].points needs at least 2 [x, y, z] points")
    return pts[:, :3]


def _num(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return math.nan
    return float(v)


class _Checker:
    def __init__(self, cfg: CellConfig, material: Material) -> None:
        lim = cfg.limits
        self.lo = np.asarray(lim.workspace_min_mm, dtype=float)
        self.hi = np.asarray(lim.workspace_max_mm, dtype=float)
        self.vmax = lim.max_speed_mm_min
        self.vmin = lim.min_weld_speed_mm_min
        self.allow_outside = lim.allow_outside_envelope
        self.source_i = (0.0, lim.source_current_max_a)
        self.source_wfs = (0.0, lim.source_wfs_max_m_min)
        r = material.ribeiro
        self.env_i = (r.i_min_a, r.i_max_a)
        self.env_wfs = (r.wfs_min_m_min, r.wfs_max_m_min)
        self.ambient = lim.ambient_c
        self.tmax = lim.max_part_temperature_c
        self.material = material.name
        self.out: list[Violation] = []

    def points(self, pts: np.ndarray, li: int, pi: int) -> None:
        bad = ~np.all(np.isfinite(pts), axis=1) | np.any(pts < self.lo, axis=1) | np.any(pts > self.hi, axis=1)
        for k in np.flatnonzero(bad)[:1]:
            x, y, z = (float(v) for v in pts[k])
            self.out.append(Violation(li, pi, int(k), f"({x:.6g}, {y:.6g}, {z:.6g}) mm lies outside the workspace "
                                      f"{tuple(float(v) for v in self.lo)}..{tuple(float(v) for v in self.hi)} mm"))
        extra = int(np.count_nonzero(bad)) - 1
        self.out.extend(Violation(li, pi, None, "point outside the workspace") for _ in range(max(0, extra)))

    def process(self, p: dict[str, Any], li: int, pi: int) -> None:
        s = _num(p.get("speed_mm_min"))
        if not (0.0 < s <= self.vmax):
            self.out.append(Violation(li, pi, None, f"speed_mm_min {s:g} is outside (0, {self.vmax:g}] mm/min "
                                      "(limits.max_speed_mm_min)"))
        elif s < self.vmin:
            self.out.append(Violation(li, pi, None, f"speed_mm_min {s:g} is below the slowest weld "
                                      f"{self.vmin:g} mm/min (limits.min_weld_speed_mm_min): a standing torch"))
        outside = p.get("inside_envelope") is False and self.allow_outside
        for key, val, env, src, unit in (("current_a", _num(p.get("current_a")), self.env_i, self.source_i, "A"),
                                         ("wfs_m_min", _num(p.get("wfs_m_min")), self.env_wfs, self.source_wfs,
                                          "m/min")):
            lo, hi = src if outside else env
            ok = (lo < val <= hi) if outside else (lo - 1e-9 <= val <= hi + 1e-9)
            if not ok:
                rng = f"the power source's range ({lo:g}, {hi:g}]" if outside \
                    else f"{self.material}'s envelope [{lo:g}, {hi:g}]"
                self.out.append(Violation(li, pi, None, f"{key} {val:g} {unit} is outside {rng}"))

    def interpass(self, layer: dict[str, Any], li: int) -> None:
        ip = layer.get("interpass")
        if ip is None:
            return
        t = _num(ip.get("max_temperature_c")) if isinstance(ip, dict) else math.nan
        if not (self.ambient < t <= self.tmax):
            self.out.append(Violation(li, None, None, f"interpass max_temperature_c {t:g} °C is outside "
                                      f"({self.ambient:g}, {self.tmax:g}] (ambient, limits.max_part_temperature_c)"))
        d = _num(ip.get("dwell_s")) if isinstance(ip, dict) else math.nan
        if not (0.0 <= d <= 3600.0):
            self.out.append(Violation(li, None, None, f"interpass dwell_s {d:g} s is outside [0, 3600]"))


def _counts(layers: list[Any]) -> None:
    n_pass = 0
    n_pts = 0
    for li, la in enumerate(layers):
        passes = la.get("passes") if isinstance(la, dict) else None
        if not isinstance(passes, list):
            raise InputError(f"job file: layers[{li}].passes must be a list")
        n_pass += len(passes)
        for pi, p in enumerate(passes):
            pts = p.get("points") if isinstance(p, dict) else None
            if not isinstance(pts, list):
                raise InputError(f"job file: layers[{li}].passes[{pi}].points must be a list")
            if len(pts) > MAX_POINTS_PER_PASS:
                raise InputError(f"job file: layers[{li}].passes[{pi}] has {len(pts)} points, over the limit "
                                 f"of {MAX_POINTS_PER_PASS}")
            n_pts += len(pts)
    if n_pass == 0:
        raise InputError("job file: no passes in any layer; nothing to build")
    if n_pass > MAX_PASSES:
        raise InputError(f"job file: {n_pass} passes, over the limit of {MAX_PASSES}")
    if n_pts > MAX_POINTS:
        raise InputError(f"job file: {n_pts} points, over the limit of {MAX_POINTS}")


def violations(job: JobJSON, cfg: CellConfig, material: Material) -> list[Violation]:
    """Everything in the job the cell cannot do, in job order (empty: the job may run)."""
    if not isinstance(job, dict) or not isinstance(job.get("layers"), list) or not job["layers"]:
        raise InputError("job file: no layers (not a cell-job/1 job)")
    _counts(job["layers"])
    t = _transform(job)
    c = _Checker(cfg, material)
    for li, la in enumerate(job["layers"]):
        idx = la.get("index", li) if isinstance(la.get("index", li), int) else li
        c.interpass(la, idx)
        for pi, p in enumerate(la["passes"]):
            if not isinstance(p, dict):
                raise InputError(f"job file: layers[{li}].passes[{pi}] must be an object")
            pts = _points(p, li, pi)
            if t is not None:
                with np.errstate(all="ignore"):
                    pts = pts @ t[:3, :3].T + t[:3, 3]
            c.points(pts, idx, pi)
            c.process(p, idx, pi)
    return c.out


def check_job(job: JobJSON, cfg: CellConfig, material: Material, source: str = "job") -> None:
    """Raise JobCheckError naming the first violation and how many there are; None if the job fits."""
    found = violations(job, cfg, material)
    if found:
        raise JobCheckError(source, found)


@lru_cache(maxsize=16)
def _material(name: str) -> Material:
    # cached: the API checks the job again in open_job while the bus cycles run, and a YAML
    # load plus validation takes tens of ms on a loaded machine
    from core.config import load_material

    return load_material(name)


def job_material(job: JobJSON, cfg: CellConfig) -> Material:
    """The material the job was planned for (its `material.name`), else the cell's."""
    load_material = _material
    m = job.get("material") if isinstance(job, dict) else None
    name = m.get("name") if isinstance(m, dict) else None
    if isinstance(name, str) and name and "/" not in name and "\\" not in name and not name.startswith("."):
        try:
            return load_material(name)
        except CellError:  # an unknown name falls back to the cell's material
            pass
    return load_material(cfg.cell.material)

"""The job checked against the cell before any device is touched (docs/contract.md §6, issue 14).

Pure: the typed job (read and checked field by field once: controller/job/read.py, which also
bounds the pass and point counts), the cell config and the material in, a list of violations
out. Every point of every pass must lie inside the workspace after the job's alignment transform,
every speed in (0, max_speed], every current and wire feed inside the material's envelope (or,
for a pass planned with `inside_envelope: false` on a cell that allows it, inside the power
source's range), every interpass limit inside (ambient, max part temperature).

A job is checked once per cell: `cell run` checks it before any device is touched, the API's
`open_job` asks again and finds it already passed for the same limits and material.
"""
from __future__ import annotations

from functools import lru_cache
import weakref
from dataclasses import dataclass

import numpy as np

from controller.job.model import CellJob
from planner.job import Layer, Pass
from core.config import CellConfig
from core.errors import CellError, InputError
from core.material import Material


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

    def process(self, p: Pass, li: int, pi: int) -> None:
        """The pass's speed, current and wire feed; a cell-job/2 pass's every segment (the first
        one outside named: `speed_mm_min[k]`)."""
        sp = p.speeds()
        k, s = _worst(sp, (sp <= 0.0) | (sp > self.vmax) | (sp < self.vmin))
        key = "speed_mm_min" if p.seg_speed_mm_min is None else f"speed_mm_min[{k}] (segment {k})"
        if not (0.0 < s <= self.vmax):
            self.out.append(Violation(li, pi, None, f"{key} {s:g} is outside (0, {self.vmax:g}] mm/min "
                                      "(limits.max_speed_mm_min)"))
        elif s < self.vmin:
            self.out.append(Violation(li, pi, None, f"{key} {s:g} is below the slowest weld "
                                      f"{self.vmin:g} mm/min (limits.min_weld_speed_mm_min): a standing torch"))
        outside = not p.inside_envelope and self.allow_outside
        for key, vals, seg, env, src, unit in (
                ("current_a", np.array([p.current_a]), False, self.env_i, self.source_i, "A"),
                ("wfs_m_min", p.wire_feeds(), p.seg_wfs_m_min is not None, self.env_wfs, self.source_wfs, "m/min")):
            lo, hi = src if outside else env
            ok_all = ((lo < vals) & (vals <= hi)) if outside else ((lo - 1e-9 <= vals) & (vals <= hi + 1e-9))
            k, val = _worst(vals, ~ok_all)
            ok = bool(ok_all.all())
            if not ok:
                rng = f"the power source's range ({lo:g}, {hi:g}]" if outside \
                    else f"{self.material}'s envelope [{lo:g}, {hi:g}]"
                name = f"{key}[{k}] (segment {k})" if seg else key
                self.out.append(Violation(li, pi, None, f"{name} {val:g} {unit} is outside {rng}"))

    def interpass(self, layer: Layer, li: int) -> None:
        ip = layer.interpass
        if ip is None:
            return
        t = ip.max_temperature_c
        if not (self.ambient < t <= self.tmax):
            self.out.append(Violation(li, None, None, f"interpass max_temperature_c {t:g} °C is outside "
                                      f"({self.ambient:g}, {self.tmax:g}] (ambient, limits.max_part_temperature_c)"))
        d = ip.dwell_s
        if not (0.0 <= d <= 3600.0):
            self.out.append(Violation(li, None, None, f"interpass dwell_s {d:g} s is outside [0, 3600]"))


def violations(job: CellJob, cfg: CellConfig, material: Material) -> list[Violation]:
    """Everything in the job the cell cannot do, in job order (empty: the job may run)."""
    _something_to_build(job, "job file")
    al = job.alignment
    t = al.transform if al is not None else None
    c = _Checker(cfg, material)
    for la in job.layers:
        c.interpass(la, la.index)
        for pi, p in enumerate(la.passes):
            pts = p.points
            if t is not None:
                with np.errstate(all="ignore"):
                    pts = pts @ t[:3, :3].T + t[:3, 3]
            c.points(pts, la.index, pi)
            c.process(p, la.index, pi)
    return c.out


def _worst(values: np.ndarray, bad: np.ndarray) -> tuple[int, float]:
    """The first value where `bad` is true, with its index; else the first value."""
    hit = np.flatnonzero(bad)
    k = int(hit[0]) if len(hit) else 0
    return k, float(values[k]) if len(values) else 0.0


def _something_to_build(job: CellJob, source: str) -> None:
    if not any(la.passes for la in job.layers):
        raise InputError(f"{source}: no passes in any layer; nothing to build")


# the jobs that passed, per cell limits and material: the API's open_job finds a job `cell run`
# checked before any device was touched, and does not walk its points again
_passed: weakref.WeakKeyDictionary[CellJob, set[tuple[str, str]]] = weakref.WeakKeyDictionary()


def check_job(job: CellJob, cfg: CellConfig, material: Material, source: str = "job") -> None:
    """Raise JobCheckError naming the first violation and how many there are; None if the job fits."""
    key = (cfg.limits.model_dump_json(), material.name)
    if key in _passed.get(job, ()):
        return
    _something_to_build(job, source)
    found = violations(job, cfg, material)
    if found:
        raise JobCheckError(source, found)
    _passed.setdefault(job, set()).add(key)


@lru_cache(maxsize=16)
def _material(name: str) -> Material:
    # cached: the API checks the job again in open_job while the bus cycles run, and a YAML
    # load plus validation takes tens of ms on a loaded machine
    from core.config import load_material

    return load_material(name)


def job_material(job: CellJob, cfg: CellConfig) -> Material:
    """The material the job was planned for (its `material.name`), else the cell's."""
    load_material = _material
    name = job.job.material.get("name")
    if isinstance(name, str) and name and "/" not in name and "\\" not in name and not name.startswith("."):
        try:
            return load_material(name)
        except CellError:  # an unknown name falls back to the cell's material
            pass
    return load_material(cfg.cell.material)

"""From planned beads to welded passes: each bead's welding point, its mass balance, the cell's limits.

* Welding point: the process model's (Ribeiro) current and wire feed for the bead's width at the
  layer height (`Process.point`); a bead whose width the envelope cannot weld gets the nearest
  weldable width toward the nominal one.
* Mass balance (docs/contract.md §3.7): the travel speed at which π·D²/4 × WFS / v equals the section
  the bead fills (its share × layer height).
* Plan-time limits (docs/contract.md §3.10): a balanced speed above the cell's `max_speed_mm_min` keeps
  the speed at the limit and lowers the wire feed instead (the current follows the synergic
  line), below `min_weld_speed_mm_min` it raises it; a wire feed that leaves the material's
  envelope is refused naming the bead, or under `--allow-outside` planned with
  `inside_envelope: false` inside the power source's range (what `cell run`'s job check accepts).

Pure: no I/O, no clocks.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from dataclasses import dataclass

import numpy as np
import shapely

from core.errors import EnvelopeError
from planner.balance import balance_error, balanced_speed
from planner.job import Pass
from planner.path2d import Path2D
from planner.process import ProcessPoint, current_for_wfs, envelope_violations, inverse
from planner.slicer import LayerSlice

if TYPE_CHECKING:  # annotations only: `cell plan` passes a remembered material (core.config_cache) and
    # never imports pydantic
    from core.material import Material


@dataclass(frozen=True)
class CellLimits:
    """The cell's limits a plan must respect (config/cell.yaml `limits`; these defaults are its)."""

    max_speed_mm_min: float = 6000.0
    min_speed_mm_min: float = 30.0
    source_current_max_a: float = 500.0
    source_wfs_max_m_min: float = 25.0


class Process:
    """Welding points per bead width at the layer height, cached."""

    def __init__(self, material: Material, height: float, allow_outside: bool, nominal: float) -> None:
        self.material, self.height, self.allow, self.nominal = material, height, allow_outside, nominal
        self.cache: dict[float, ProcessPoint] = {}

    def point(self, width: float) -> ProcessPoint:
        w = round(float(width), 3)
        if w not in self.cache:
            self.cache[w] = self._solve(w)
        return self.cache[w]

    def _solve(self, w: float) -> ProcessPoint:
        try:
            pp = inverse(self.material, w, self.height, allow_outside=self.allow)
            # Under --allow-outside the synergic line is extrapolated: never to a wire feed or a
            # current of nothing (the bead cannot be welded at all).
            if (pp.wfs_m_min > 0.0 and pp.current_a > 0.0) or w == round(self.nominal, 3):
                return pp
        except EnvelopeError:
            if w == round(self.nominal, 3):
                raise
        # A gap bead whose width the envelope cannot weld: the nearest weldable width toward nominal.
        for cand in np.linspace(w, self.nominal, 9)[1:]:
            try:
                return inverse(self.material, round(float(cand), 3), self.height)
            except EnvelopeError:
                continue
        return inverse(self.material, self.nominal, self.height, allow_outside=self.allow)


def as_welded(p: Path2D, proc: Process) -> Path2D:
    """The bead at the width the process welds (a gap bead may come out wider than its pocket);
    its share (the section it fills) is kept."""
    w = proc.point(p.width_mm).width_mm
    if abs(w - p.width_mm) < 1e-9:
        return p
    return Path2D(p.role, p.points, w, p.closed, p.share_mm, p.lone)


@dataclass(frozen=True)
class Weld:
    """A pass's process numbers and what the limits said about them."""

    current_a: float
    speed_mm_min: float
    wfs_m_min: float
    inside_envelope: bool
    adjusted: bool  # the wire feed was moved off the width's point to keep the speed in the cell's range
    problem: str | None  # why the cell cannot weld it (None: it can)


def balanced_weld(pp: ProcessPoint, filled_mm2: float, material: Material, lim: CellLimits) -> Weld:
    """Current, speed and wire feed at which a bead of this welding point lays `filled_mm2` per mm."""
    d = material.wire_diameter_mm
    speed = balanced_speed(d, pp.wfs_m_min, filled_mm2)
    if lim.min_speed_mm_min <= speed <= lim.max_speed_mm_min:
        return Weld(pp.current_a, speed, pp.wfs_m_min, pp.inside_envelope, False, None)
    v = float(np.clip(speed, lim.min_speed_mm_min, lim.max_speed_mm_min))
    wfs = filled_mm2 * v / (np.pi * d * d / 4.0) / 1000.0  # the wire feed that balances at the limit
    cur = float(current_for_wfs(material, wfs))
    broken = envelope_violations(material, cur, wfs)
    why = (f"{speed:.0f} mm/min at {pp.wfs_m_min:.2f} m/min, "
           + ("above the cell's max speed" if speed > v else "below the cell's slowest weld")
           + f" {v:g} mm/min")
    problem = None
    if broken:
        problem = f"{why}; at {v:g} mm/min it needs {broken[0]}"
        if cur > lim.source_current_max_a or wfs > lim.source_wfs_max_m_min or wfs <= 0.0 or cur <= 0.0:
            problem += " and the power source cannot weld it (limits.source_*)"
    return Weld(cur, v, wfs, not broken, True, problem)


def bead_name(index: int, p: Path2D) -> str:
    c = p.points.mean(axis=0)
    return (f"pass {index} ({p.role} bead at ({c[0]:.1f}, {c[1]:.1f}), {p.width_mm:.2f} mm wide, "
            f"{p.length:.1f} mm long)")


def weld_passes(paths: list[Path2D], sl: LayerSlice, z: float, proc: Process, lim: CellLimits,
                findings: list[tuple[str, bool]]) -> tuple[list[Pass], float, int]:
    """The layer's passes; (passes, worst per-pass balance error, passes whose wire feed was moved).

    `findings` receives (message, fatal even under --allow-outside) for beads the cell cannot weld.
    """
    nrm, near = _boundary_normals(paths, sl)
    out: list[Pass] = []
    worst, adjusted = 0.0, 0
    d = proc.material.wire_diameter_mm
    for i, p in enumerate(paths):
        pp = proc.point(p.width_mm)
        pts = np.column_stack([p.points, np.full(len(p.points), z)])
        normals = nrm[near[id(p)]] if nrm is not None and id(p) in near else None
        filled = max(p.share_mm, 0.05 * p.width_mm) * proc.height
        wd = balanced_weld(pp, filled, proc.material, lim)
        speed = round(wd.speed_mm_min, 1)
        worst = max(worst, balance_error(d, round(wd.wfs_m_min, 3), speed, filled))  # as written in the job
        adjusted += wd.adjusted
        if wd.problem is not None:
            hard = "power source" in wd.problem
            findings.append((f"layer {sl.index}: {bead_name(i, p)} needs {wd.problem}", hard))
        out.append(Pass(p.role, pp.width_mm, wd.current_a, speed, wd.wfs_m_min, pts, normals,
                        inside_envelope=wd.inside_envelope))
    return out, worst, adjusted


def _boundary_normals(paths: list[Path2D], sl: LayerSlice) -> tuple[np.ndarray | None, dict[int, np.ndarray]]:
    """The layer's contour normals, and per boundary bead (by id) its points' nearest contour points.

    Boundary beads carry the facet normals: perimeters, lone beads, and gap beads that run along
    the outline (within 3/4 of their width: the one bead of a wall a little wider than a bead).
    A wall's surface normal gives its build direction for a 5-axis plan (planner/five_axis.py)."""
    closed = [c for c in sl.contours if c.closed]
    cand = [p for p in paths if p.role in ("perimeter", "gap") or p.lone]
    near: dict[int, np.ndarray] = {}
    if not (cand and closed):
        return None, near
    cpts = np.vstack([c.points for c in closed])[:, :2]
    idx = _nearest(np.vstack([p.points for p in cand]), cpts)  # one query for the whole layer
    for p, k in zip(cand, np.split(idx, np.cumsum([len(p.points) for p in cand])[:-1])):
        along = p.role == "gap" and not p.lone and bool(
            (np.linalg.norm(cpts[k] - p.points, axis=1) <= 0.75 * p.width_mm).all())
        if p.role == "perimeter" or p.lone or along:
            near[id(p)] = k
    return np.vstack([c.normals for c in closed]), near


def _nearest(q: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Index of the nearest contour point for each query point (shapely's STRtree: no scipy import)."""
    tree = shapely.STRtree(shapely.points(pts))
    hit = tree.query_nearest(shapely.points(q), all_matches=False)
    out = np.zeros(len(q), dtype=np.int64)
    out[hit[0]] = hit[1]
    return out

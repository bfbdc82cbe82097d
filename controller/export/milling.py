"""Milling programs of a near-net build's top faces (`cell finish plan`, `cell export --finish`).

Pure: the job (typed) and its CAD's triangles in, a FinishPlan and G-code lines out
(docs/machining.md "`cell finish plan`"):
- the region: the CAD's highest horizontal faces (their xy bounds); a repair job's region and
  `machining.margin_mm` within them;
- the stock: the plan's model of the deposit, each layer's passes widened by their width at the
  layer's z, the CAD's top where no layer covers;
- the plan: planner/finish.py with the cutter and machining settings of cell.yaml;
- the program: `$32=0` (laser mode off: grbl would stop the spindle on every rapid), the tool change
  of the firmware (grblHAL `T M6`, grbl 1.1h a programmed pause), then the passes
  (controller/motion/mill.py `program_lines`) in the frame `transform` takes them to.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from controller.job.model import CellJob
from controller.motion.mill import program_lines, tool_change_lines
from core.config import CellConfig
from core.errors import InputError
from core.tools import Cutter
from planner.dropcutter import ToolShape
from planner.finish import Cut, FinishPlan, Surface, cad_top, plan_finish

F = NDArray[np.float64]
FIRMWARES = ("grblhal", "grbl")


@dataclass(frozen=True)
class TopFinish:
    plan: FinishPlan
    tool: str
    cutter: Cutter
    region: tuple[float, float, float, float]
    min_stock_mm: float | None     # the planned top over CAD, lowest cell (negative: the plan leaves it short)

    def summary(self) -> dict[str, Any]:
        p = self.plan
        return {"tool": self.tool, "passes": len(p.passes), "removal_mm3": round(p.removal_mm3, 2),
                "est_time_s": round(p.est_time_s, 1),
                "min_stock_mm": None if self.min_stock_mm is None else round(self.min_stock_mm, 4),
                "scallop_mm": round(p.scallop_mm, 5), "stepover_mm": round(p.stepover_mm, 4),
                "levels": p.levels, "region_mm": [round(v, 3) for v in self.region]}


def top_region(tri: F, where: str) -> tuple[float, float, float, float]:
    """The xy bounds of the CAD's highest horizontal faces."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    up = n[:, 2] / np.maximum(np.linalg.norm(n, axis=1), 1e-12) > 0.99
    zt = tri[:, :, 2].max()
    top = tri[up & (tri[:, :, 2].min(axis=1) >= zt - 1e-3)]
    if not len(top):
        raise InputError(f"{where}: the CAD has no horizontal top face to finish")
    lo, hi = top[:, :, :2].reshape(-1, 2).min(axis=0), top[:, :, :2].reshape(-1, 2).max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def planned_top(job: CellJob, region: tuple[float, float, float, float], cell_mm: float = 0.5) -> Surface:
    """The plan's deposit top over the region: per cell the highest layer whose passes cover it."""
    # lazy: shapely loads only when this path runs (start-up time)
    import shapely
    from shapely.geometry import LineString, Point
    from shapely.ops import unary_union

    xs = np.arange(region[0], region[2] + 1e-9, cell_mm)
    ys = np.arange(region[1], region[3] + 1e-9, cell_mm)
    gx, gy = np.meshgrid(xs, ys)
    top = np.full(gx.shape, np.nan)
    for L in sorted(job.layers, key=lambda x: x.z_mm):
        shapes = []
        for ps in L.passes:
            pts = [(float(q[0]), float(q[1])) for q in ps.points.tolist()]
            w = (ps.width_mm or job.job.bead.width_mm) / 2
            shapes.append(LineString(pts).buffer(w) if len(pts) >= 2 else Point(pts[0]).buffer(w))
        if shapes:
            inside = shapely.contains_xy(unary_union(shapes), gx, gy)
            top = np.where(inside, L.z_mm, top)
    return Surface(top, (float(region[0]), float(region[1])), cell_mm)


def finish_top(job: CellJob, tri: F, cell: CellConfig, tool: str | None, where: str) -> TopFinish:
    """Rough and finish the job's top faces to its CAD (`tri`, the job's frame) with `tool`
    (None: machining.cutter)."""
    try:
        name, cutter = cell.tools.cutter(tool or cell.machining.cutter)
    except KeyError as exc:
        raise InputError(f"--tool: {exc.args[0]}") from None
    region = top_region(tri, where)
    rb = job.repair.bounds_mm if job.repair is not None else None
    if rb is not None:   # a repair: its region and the margin, within the top faces
        mg = cell.machining.margin_mm
        region = (max(region[0], float(rb[0][0]) - mg), max(region[1], float(rb[0][1]) - mg),
                  min(region[2], float(rb[1][0]) + mg), min(region[3], float(rb[1][1]) + mg))
    stock = planned_top(job, region)
    gx, gy = np.meshgrid(*stock.xy())
    cadz = cad_top(tri, np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
    h = np.where(np.isfinite(stock.heights), stock.heights, cadz)
    over = h - cadz
    m = cell.machining
    cut = Cut(name, ToolShape(cutter.type, cutter.radius_mm), cutter.max_depth_of_cut_mm, cutter.max_stepover_mm,
              cutter.feed_mm_min, cell.limits.travel_speed_mm_min)
    plan = plan_finish(tri, Surface(h, stock.origin, stock.cell_mm), region, cut,
                       finish_stock_mm=m.finish_stock_mm, scallop_mm=m.scallop_mm)
    ok = np.isfinite(over)
    return TopFinish(plan, name, cutter, region, float(np.min(over[ok])) if ok.any() else None)


def milling_program(fin: TopFinish, firmware: str, transform: F | None = None) -> list[str]:
    """The whole milling program of a file: `$32=0`, the tool change, the passes, `M5`."""
    if firmware not in FIRMWARES:
        raise InputError(f"--firmware {firmware}: one of {', '.join(FIRMWARES)}")
    tf = np.eye(4) if transform is None else np.asarray(transform, dtype=float)
    c = fin.cutter
    return ["$32=0", *tool_change_lines(firmware, c.number, fin.tool, c.length_offset_mm),
            *program_lines(fin.plan, tf, c)]

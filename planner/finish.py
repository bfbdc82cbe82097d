"""Finish machining plans: rough a deposit to CAD + finishing stock, then finish it to CAD (pure).

Surfaces machined from above (docs/contract.md §4 "Finish machining", docs/machining.md):
- the stock is the deposit's top as probed, a height map over the region (`Surface`);
- roughing: z levels from the stock's top down to CAD + `finish_stock_mm`, at most the cutter's
  `max_depth_of_cut_mm` apart (less the roughing scallop); each level a zigzag raster at the
  cutter's `max_stepover_mm` whose every cutter location stands at least at the level and at
  the drop-cutter on the CAD mesh + finishing stock; where the tool meets no stock, no pass;
- finishing: one zigzag raster whose cutter locations are the drop-cutter on the CAD mesh, the
  stepover chosen for a scallop of at most `scallop_mm` (ball: h = R − √(R² − (s/2)²));
- the gouge check: every cutter location of every pass, and the middle of every move between
  them, against the exact drop-cutter on the CAD mesh with the tool's shape; a plan with a tool
  below CAD is refused (`GougeError`), never emitted.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from planner.dropcutter import F, ToolShape, drop_mesh, drop_map, scallop_height, stepover_for_scallop

GOUGE_TOL_MM = 1e-6


class GougeError(ValueError):
    """A planned tool location lies below the CAD surface."""


@dataclass(frozen=True)
class Surface:
    """A height map: `heights[j, i]` the top at x = x0 + i·cell, y = y0 + j·cell (NaN: unknown)."""

    heights: F
    origin: tuple[float, float]
    cell_mm: float

    def xy(self) -> tuple[F, F]:
        ny, nx = self.heights.shape
        xs: F = self.origin[0] + np.arange(nx, dtype=float) * self.cell_mm
        ys: F = self.origin[1] + np.arange(ny, dtype=float) * self.cell_mm
        return xs, ys

    def sample(self, x: F, y: F) -> F:
        """Nearest grid value at (x, y) (NaN outside)."""
        ny, nx = self.heights.shape
        i = np.rint((np.asarray(x) - self.origin[0]) / self.cell_mm).astype(np.int64)
        j = np.rint((np.asarray(y) - self.origin[1]) / self.cell_mm).astype(np.int64)
        ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        out = np.full(np.shape(i), np.nan)
        out[ok] = self.heights[j[ok], i[ok]]
        return out


@dataclass(frozen=True)
class Cut:
    """One tool: its shape and its limits (from cell.yaml's tools)."""

    name: str
    shape: ToolShape
    max_depth_of_cut_mm: float
    max_stepover_mm: float
    feed_mm_min: float
    rapid_mm_min: float = 3000.0


@dataclass(frozen=True)
class Pass:
    """One continuous cutting move: cutter locations (tip, CAD frame) at the feed."""

    kind: str            # "rough" | "finish"
    points: F            # (k, 3)


@dataclass(frozen=True)
class FinishPlan:
    tool: str
    passes: tuple[Pass, ...]
    removal_mm3: float
    est_time_s: float
    scallop_mm: float
    stepover_mm: float
    levels: int
    gouge_mm: float      # how far the lowest tool location lies below CAD (≤ 0: none)
    safe_z_mm: float

    def summary(self) -> dict[str, float | int | str]:
        return {"tool": self.tool, "passes": len(self.passes), "removal_mm3": round(self.removal_mm3, 2),
                "est_time_s": round(self.est_time_s, 1), "scallop_mm": round(self.scallop_mm, 5),
                "stepover_mm": round(self.stepover_mm, 4), "levels": self.levels}


def surface_from_points(pts: F, region: tuple[float, float, float, float], cell_mm: float = 0.5) -> Surface:
    """A height map over `region` (x0, y0, x1, y1) from scattered points (n, 3): linear inside
    their hull, the nearest point outside it."""
    # lazy: scipy's interpolate loads only when this path runs (start-up time)
    from scipy.interpolate import griddata

    x0, y0, x1, y1 = region
    xs = np.arange(x0, x1 + 1e-9, cell_mm)
    ys = np.arange(y0, y1 + 1e-9, cell_mm)
    gx, gy = np.meshgrid(xs, ys)
    p = np.asarray(pts, dtype=float)
    if len(p) >= 3:
        lin = griddata(p[:, :2], p[:, 2], (gx, gy), method="linear")
    else:
        lin = np.full(gx.shape, np.nan)
    near = griddata(p[:, :2], p[:, 2], (gx, gy), method="nearest")
    return Surface(np.where(np.isfinite(lin), lin, near), (float(x0), float(y0)), float(cell_mm))


def stock_surface(triangles: F, pts: F, region: tuple[float, float, float, float], *, grow_mm: float = 2.0,
                  ripple_mm: float = 0.5, cell_mm: float = 0.5) -> Surface:
    """The stock to machine over `region`: the CAD top, and within `grow_mm` of the probed touches
    (n, 3) the surface through them raised by `ripple_mm` (the deposit between touches)."""
    probed = surface_from_points(pts, region, cell_mm)
    xs, ys = probed.xy()
    gx, gy = np.meshgrid(xs, ys)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    cad = cad_top(triangles, xy).reshape(gx.shape)
    p = np.asarray(pts, dtype=float)
    d = np.min(np.hypot(xy[:, None, 0] - p[None, :, 0], xy[:, None, 1] - p[None, :, 1]), axis=1).reshape(gx.shape)
    near = (d <= grow_mm) | np.isfinite(_linear(p, gx, gy))   # inside the touches' hull or near one
    h = np.where(near, np.fmax(probed.heights + ripple_mm, cad), cad)
    return Surface(np.where(np.isfinite(cad), h, np.nan), probed.origin, cell_mm)


def _linear(p: F, gx: F, gy: F) -> F:
    # lazy: scipy's interpolate loads only when this path runs (start-up time)
    from scipy.interpolate import griddata

    if len(p) < 3:
        return np.full(gx.shape, np.nan)
    out: F = griddata(p[:, :2], p[:, 2], (gx, gy), method="linear")
    return out


def cad_top(triangles: F, xy: F) -> F:
    """The CAD's top z straight above each xy (-inf off the part)."""
    return drop_mesh(ToolShape("flat", 1e-6), triangles, xy)


def raster(region: tuple[float, float, float, float], stepover: float, spacing: float) -> list[F]:
    """Zigzag rows along x, `stepover` apart in y, points `spacing` apart: (k, 2) each."""
    x0, y0, x1, y1 = region
    ny = max(1, int(math.ceil((y1 - y0) / stepover - 1e-9)))
    ys = np.linspace(y0, y1, ny + 1)
    nx = max(1, int(math.ceil((x1 - x0) / spacing - 1e-9)))
    xs = np.linspace(x0, x1, nx + 1)
    rows = []
    for k, y in enumerate(ys):
        xr = xs if k % 2 == 0 else xs[::-1]
        rows.append(np.column_stack([xr, np.full(len(xr), y)]))
    return rows


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges where mask is true, each widened by one point on either side."""
    out: list[tuple[int, int]] = []
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return out
    cuts = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[idx[0]], idx[cuts + 1]])
    ends = np.concatenate([idx[cuts], [idx[-1]]])
    for s, e in zip(starts, ends):
        out.append((max(int(s) - 1, 0), min(int(e) + 2, len(mask))))
    return out


def _rough_levels(top: float, floor: float, doc: float) -> list[float]:
    if top <= floor + 1e-6:
        return []
    n = max(1, int(math.ceil((top - floor) / doc - 1e-9)))
    return [top - (k + 1) * (top - floor) / n for k in range(n)]


def plan_finish(triangles: F, stock: Surface, region: tuple[float, float, float, float], cut: Cut, *,
                finish_stock_mm: float = 0.2, scallop_mm: float = 0.01, clearance_mm: float = 5.0) -> FinishPlan:
    """Rough and finish `region` (x0, y0, x1, y1, CAD frame) from the probed `stock` to the CAD mesh."""
    tri = np.asarray(triangles, dtype=float).reshape(-1, 3, 3)
    shape = cut.shape
    spacing = min(0.5, shape.radius_mm / 4.0)
    # roughing: the stock dropped on by the tool tells where a level meets metal
    s_drop = Surface(drop_map(shape, stock.heights, stock.origin, stock.cell_mm), stock.origin, stock.cell_mm)
    r_step = cut.max_stepover_mm
    r_scallop = scallop_height(shape, r_step) if shape.kind == "ball" else 0.0
    doc = max(cut.max_depth_of_cut_mm - r_scallop, 0.25 * cut.max_depth_of_cut_mm)
    rows = raster(region, r_step, spacing)
    pts = np.vstack(rows)
    floor = drop_mesh(shape, tri, pts) + finish_stock_mm
    top = float(np.nanmax(stock.heights))
    finite = floor[np.isfinite(floor)]
    passes: list[Pass] = []
    levels = _rough_levels(top, float(finite.min()) if len(finite) else top, doc)
    sd = s_drop.sample(pts[:, 0], pts[:, 1])
    for lv in levels:
        z = np.maximum(lv, floor)
        meets = np.isfinite(z) & (np.nan_to_num(sd, nan=-np.inf) > z + 1e-6)
        for a, b in _runs(meets):
            seg = np.column_stack([pts[a:b], z[a:b]])
            passes.append(Pass("rough", seg[np.isfinite(seg[:, 2])]))
    f_step = stepover_for_scallop(shape, scallop_mm, cut.max_stepover_mm)
    frows = raster(region, f_step, spacing)
    fxy = np.vstack(frows)
    fin = np.column_stack([fxy, drop_mesh(shape, tri, fxy)])
    fin = fin[np.isfinite(fin[:, 2])]
    passes.append(Pass("finish", fin))
    passes = [p for p in passes if len(p.points) >= 2]
    gouge = gouge_depth(tri, shape, passes)
    if gouge > GOUGE_TOL_MM:
        raise GougeError(f"finish plan: the {cut.name} would cut {gouge:.4f} mm below CAD; not emitted")
    safe = max(top, float(fin[:, 2].max())) + clearance_mm
    removal = stock_above_cad(tri, stock)
    return FinishPlan(cut.name, tuple(passes), removal, _time_s(passes, cut, safe),
                      scallop_height(shape, f_step), f_step, len(levels), gouge, safe)


def gouge_depth(triangles: F, shape: ToolShape, passes: list[Pass]) -> float:
    """How far below the CAD drop-cutter any tool location lies, the moves' middles included."""
    if not passes:
        return -math.inf
    allp = np.vstack([np.vstack([p.points, (p.points[1:] + p.points[:-1]) / 2.0]) for p in passes])
    need = drop_mesh(shape, triangles, allp[:, :2])
    ok = np.isfinite(need)
    return float(np.max(need[ok] - allp[ok, 2])) if np.any(ok) else -math.inf


def stock_above_cad(triangles: F, stock: Surface) -> float:
    """The volume (mm³) of the stock above the CAD over the stock's grid."""
    xs, ys = stock.xy()
    gx, gy = np.meshgrid(xs, ys)
    cad = cad_top(triangles, np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
    d = np.where(np.isfinite(cad) & np.isfinite(stock.heights), stock.heights - cad, 0.0)
    return float(np.clip(d, 0.0, None).sum() * stock.cell_mm ** 2)


def stock_margin(triangles: F, pts: F) -> F:
    """Each probed point's height above the CAD under it (mm; NaN off the part)."""
    p = np.asarray(pts, dtype=float).reshape(-1, 3)
    cad = cad_top(triangles, p[:, :2])
    return np.where(np.isfinite(cad), p[:, 2] - cad, np.nan)


def _time_s(passes: list[Pass], cut: Cut, safe: float) -> float:
    feed = sum(float(np.linalg.norm(np.diff(p.points, axis=0), axis=1).sum()) for p in passes)
    rapid = 0.0
    prev: F | None = None
    for p in passes:
        a = p.points[0]
        rapid += 2 * (safe - a[2]) + (float(np.linalg.norm(a[:2] - prev[:2])) if prev is not None else 0.0)
        prev = p.points[-1]
    return float(60.0 * (feed / cut.feed_mm_min + rapid / cut.rapid_mm_min))

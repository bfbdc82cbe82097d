"""`cell finish plan RUN_DIR|JOB [--tool T] [--out PROGRAM]`: finish a near-net build's top faces.

The stock is the plan's model of the deposit (each layer's passes widened by their width, at the
layer's z), the target the job's own CAD (a repair job's `repair.cad`, else the planned mesh
`source.file` in the job's frame); the region the CAD's top faces. Planned as the repair's
machining is (planner/finish.py, docs/machining.md); `--out` writes the milling program (machine
frame = the job's frame), with the tool change for `--firmware grblhal` (T M6) or `grbl` (M0 pause).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import InputError


def register(sub: Any) -> None:
    fp = sub.add_parser("finish", help="finish machining plans (docs/machining.md)")
    fs = fp.add_subparsers(dest="finish_cmd", required=True)
    p = fs.add_parser("plan", help="rough and finish a near-net build's top faces to its CAD")
    p.add_argument("source", metavar="RUN_DIR|JOB", help="a job file, or a run directory holding one")
    p.add_argument("--tool", metavar="T", help="a cutter of cell.yaml tools.cutters (default machining.cutter)")
    p.add_argument("--out", metavar="PROGRAM", help="write the milling program (G-code) here")
    p.add_argument("--firmware", choices=("grblhal", "grbl"), default="grblhal",
                   help="the tool change the program carries (default grblhal: T M6)")
    p.add_argument("--cell-config", metavar="FILE", help="cell.yaml (default config/cell.yaml)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(func=run_finish_plan)


def _job_path(source: str) -> Path:
    p = Path(source)
    if p.is_dir():
        found = sorted(p.glob("*.json"))
        jobs = [f for f in found if f.name.endswith("job.json")] or [f for f in found if f.name == "job.json"]
        if not jobs:
            raise InputError(f"{p}: no job file (*job.json) in this run directory; give the job file")
        return jobs[0]
    if not p.is_file():
        raise InputError(f"{p}: no such job file or run directory")
    return p


def _cad(job: Any, path: Path) -> np.ndarray:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.repair import load_cad
    from planner.mesh import read_mesh

    if job.repair is not None and job.repair.cad:
        cad: np.ndarray = np.asarray(load_cad(job, path).triangles, dtype=float)
        return cad
    src = Path(job.job.source.file)
    if not src.is_absolute():
        src = path.parent / src
    if not src.is_file():
        raise InputError(f"{path}: source.file {job.job.source.file}: no such mesh; put the planned mesh there")
    pm = read_mesh(src, job.job.source.units)
    tri: np.ndarray = np.asarray(pm.vertices, dtype=float)[np.asarray(pm.faces)].copy()
    if job.job.frame == "cad":
        tri[:, :, 2] += pm.z_shift_mm
    return tri


def _planned_top(job: Any, region: tuple[float, float, float, float], cell_mm: float = 0.5) -> Any:
    """The plan's deposit top over the region: per cell the highest layer whose passes cover it."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    import shapely
    from shapely.geometry import LineString, Point
    from shapely.ops import unary_union
    from planner.finish import Surface

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


def run_finish_plan(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.job.read import read_job
    from controller.motion.mill import program_lines, tool_change_lines
    from core.config import load_cell
    from planner.dropcutter import ToolShape
    from planner.finish import Cut, cad_top, plan_finish

    path = _job_path(args.source)
    job = read_job(path)
    cell = load_cell(args.cell_config)
    try:
        name, cutter = cell.tools.cutter(args.tool or cell.machining.cutter)
    except KeyError as exc:
        raise InputError(f"--tool: {exc.args[0]}") from None
    tri = _cad(job, path)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    up = n[:, 2] / np.maximum(np.linalg.norm(n, axis=1), 1e-12) > 0.99
    zt = tri[:, :, 2].max()
    top = tri[up & (tri[:, :, 2].min(axis=1) >= zt - 1e-3)]
    if not len(top):
        raise InputError(f"{path}: the CAD has no horizontal top face to finish")
    lo, hi = top[:, :, :2].reshape(-1, 2).min(axis=0), top[:, :, :2].reshape(-1, 2).max(axis=0)
    region = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    stock = _planned_top(job, region)
    xs = stock.xy()
    gx, gy = np.meshgrid(*xs)
    cadz = cad_top(tri, np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
    h = np.where(np.isfinite(stock.heights), stock.heights, cadz)
    stock = type(stock)(h, stock.origin, stock.cell_mm)
    over = h - cadz
    m = cell.machining
    plan = plan_finish(tri, stock, region, Cut(name, ToolShape(cutter.type, cutter.radius_mm),
                                               cutter.max_depth_of_cut_mm, cutter.max_stepover_mm, cutter.feed_mm_min,
                                               cell.limits.travel_speed_mm_min),
                       finish_stock_mm=m.finish_stock_mm, scallop_mm=m.scallop_mm)
    out = {"tool": name, "passes": len(plan.passes), "removal_mm3": round(plan.removal_mm3, 2),
           "est_time_s": round(plan.est_time_s, 1),
           "min_stock_mm": round(float(np.nanmin(over[np.isfinite(over)])), 4) if np.isfinite(over).any() else None,
           "scallop_mm": round(plan.scallop_mm, 5), "stepover_mm": round(plan.stepover_mm, 4),
           "levels": plan.levels, "region_mm": [round(v, 3) for v in region], "job": str(path)}
    if args.out:
        lines = tool_change_lines(args.firmware, cutter.number, name, cutter.length_offset_mm)
        lines += program_lines(plan, np.eye(4), cutter)
        Path(args.out).write_text("\n".join(lines) + "\n", encoding="utf-8")
        out.update(out_file=str(args.out), lines=len(lines))
    if args.json:
        emit_json(out)
    else:
        print(json.dumps(out))
    return 0

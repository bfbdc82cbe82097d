"""Finish planning speed and scallop (issue 36): `python -m bench.finish_plan [--size MM] [--repeat N]`.

A 120 × 120 × 20 mm block (the CAD) under a rippled deposit 1.4–2.2 mm high probed over a
SIZE × SIZE mm region (0.5 mm grid); `planner.finish.plan_finish` roughs and finishes it with each
cutter of the shipped cell.yaml. Prints one JSON line per cutter: the best wall time of N runs,
passes, levels, stepover, scallop, the gouge check's figure and the CL point count.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import trimesh

from core.config import load_cell
from planner.dropcutter import ToolShape
from planner.finish import Cut, Surface, plan_finish


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=float, default=100.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    cad = trimesh.creation.box(extents=(a.size + 20, a.size + 20, 20))
    cad.apply_translation((0, 0, -10))
    tri = np.asarray(cad.triangles)
    half = a.size / 2
    xs = np.arange(-half, half + 1e-9, 0.5)
    gx, gy = np.meshgrid(xs, xs)
    stock = Surface(1.8 + 0.4 * np.sin(gx / 3) * np.cos(gy / 4), (-half, -half), 0.5)
    cell = load_cell()
    for name, c in cell.tools.cutters.items():
        cut = Cut(name, ToolShape(c.type, c.radius_mm), c.max_depth_of_cut_mm, c.max_stepover_mm, c.feed_mm_min)
        best = cpu = float("inf")
        for _ in range(a.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            plan = plan_finish(tri, stock, (-half, -half, half, half), cut,
                               finish_stock_mm=cell.machining.finish_stock_mm, scallop_mm=cell.machining.scallop_mm)
            best = min(best, time.perf_counter() - t0)
            cpu = min(cpu, time.process_time() - c0)   # on a shared host the wall time is mostly others' load
        print(json.dumps({"region_mm": a.size, "wall_s": round(best, 3), "cpu_s": round(cpu, 3), **plan.summary(),
                          "gouge_mm": plan.gouge_mm, "cl_points": sum(len(p.points) for p in plan.passes)}))


if __name__ == "__main__":
    main()

"""5-axis tool axis against the part's build direction (issue 38): tilted tubes and frustums.

`python -m bench.tilt5` plans each part 5-axis and prints, per part, the largest angle between a
pass's tool axis and the wall's generator (the line its wall grows along) over every point of
every layer, and the range of the tool's tilt from vertical.
"""
from __future__ import annotations

import json
import sys

import numpy as np

from bench.parts5 import leaning_frustum, tilted_tube
from core.config import load_material
from planner.five_axis import FiveAxisOptions
from planner.job import Job
from planner.plan import PlanOptions, plan_part

# (name, flare°, lean°, wall mm, turned: the frustum turned about y; else sheared along x)
PARTS = [("tube 32° sheared, one bead", 0.0, 32.0, 5.0, False),
         ("tube 32° turned, one bead", 0.0, 32.0, 5.0, True),
         ("tube 25° turned, two perimeters", 0.0, 25.0, 9.0, True),
         ("frustum upright, flaring 20°", 20.0, 0.0, 5.0, True),
         ("frustum flaring 15°, leaning 20°", 15.0, 20.0, 5.0, True),
         ("frustum flaring 25°, leaning 15°", 25.0, 15.0, 5.0, True),
         ("frustum narrowing 15°, leaning 25°", -15.0, 25.0, 5.0, True),
         ("frustum narrowing 20°, leaning -20°", -20.0, -20.0, 5.0, True)]


def off_generator(job: Job, R: np.ndarray, flare_deg: float, centre: np.ndarray) -> tuple[float, float, float]:
    """(worst angle to the generator, min tilt, max tilt), degrees, over every layer."""
    ta = np.tan(np.radians(flare_deg))
    worst, tilts = 0.0, []
    for layer in job.layers:
        for p in layer.passes:
            q = (p.points - centre) @ R
            phi = np.arctan2(q[:, 1], q[:, 0])
            g = np.column_stack([ta * np.cos(phi), ta * np.sin(phi), np.ones(len(q))]) @ R.T
            g /= np.linalg.norm(g, axis=1, keepdims=True)
            worst = max(worst, float(np.degrees(np.arccos(np.clip((g * p.axes).sum(axis=1), -1, 1))).max()))
            tilts.append(np.degrees(np.arccos(np.clip(p.axes[:, 2], -1, 1))))
    t = np.concatenate(tilts)
    return worst, float(t.min()), float(t.max())


def main(argv: list[str] | None = None) -> int:
    mat = load_material("inconel718-1.0mm")
    rows = []
    for name, flare, lean, wall, turned in PARTS:
        if turned:
            mesh, R = leaning_frustum(flare_deg=flare, lean_deg=lean, wall=wall)
            centre = np.array([0.0, 0.0, 10.0])
        else:
            mesh = tilted_tube(r_out=20.0, wall=wall, height=6.0, tilt_deg=lean)
            R = np.array([[1.0, 0.0, np.tan(np.radians(lean))], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
            centre = np.zeros(3)
        opt = PlanOptions(width_mm=6.0 if wall < 6 else 5.0, allow_overhang=True, allow_underfill=True,
                          five_axis=FiveAxisOptions(nozzle=None))
        job = plan_part(mesh, opt, mat)
        worst, lo, hi = off_generator(job, R, flare, centre)
        rows.append({"part": name, "layers": len(job.layers), "max_off_build_direction_deg": round(worst, 2),
                     "tilt_deg": [round(lo, 2), round(hi, 2)]})
        print(json.dumps(rows[-1]))
    print(json.dumps({"worst_deg": max(r["max_off_build_direction_deg"] for r in rows)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Feed-forward figures (issue 35 item 2): the predicted top's spread per layer before and after,
and the truth: the job poured, bead by bead, into the simulated world's own height map.

    python -m bench.feedforward [--part config/parts/square-hole.stl --width 7 --layers N]
    python -m bench.feedforward --wall 100 --layers 40        # a 40-layer single-bead wall
    python -m bench.feedforward --pour ...                     # the poured feed-forward (opt-in)

For the demo part (and a single-bead wall) it plans the job twice, without and with the
feed-forward, reports the plan time and the summary's predicted spread per layer, then lays every
segment of the job into `sims.process_world.ProcessPhysics` (the simulator's physics, nominal
world of config/sim.yaml, the plan's z: `process_control: open`): the torch at the planned z, the
stick-out from the deposit under it, the current from the melting-rate relation at the segment's
wire feed, the bead's width from the model at that current and speed. Per layer: the true top's
spread along the pass centre lines (max − min, mm), its RMS error against the planned top, the
stick-out range and the share of segments whose current is outside ±10 % of the synergic line's at the segment's wire feed
(what the bead judge would call a defect).
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from controller.job.weld_path import move_values, weld_points, weld_segments
from core.config import CONFIG_DIR, load_material, load_sim
from core.material import Material
from planner.job import Job
from planner.options import PlanOptions
from planner.plan import plan_part
from sims.process_world import ProcessPhysics

STEP_MM = 6.0     # the demo's weld-move length (controller/defaults.py DEMO_MAX_STEP_MM)


def pour(job: Job, material: Material, step_mm: float = STEP_MM) -> list[dict[str, float]]:
    """Lay the job into the simulated world (nominal); per layer the truth figures."""
    phys = ProcessPhysics(material, load_sim().process)
    hm = phys.height_map("robot")
    r = material.ribeiro
    slope = (r.i_max_a - r.i_min_a) / (r.wfs_max_m_min - r.wfs_min_m_min)
    out = []
    for la in job.layers:
        ctwd, bad, n = [], 0, 0
        for p in la.passes:
            pts = weld_points(p.points, step_mm)
            v = move_values(p.speeds(), weld_segments(p.points, step_mm))
            w = move_values(p.wire_feeds(), weld_segments(p.points, step_mm))
            phys.new_bead()
            for k, (a, b) in enumerate(zip(pts, pts[1:])):
                d = np.subtract(b, a)
                phys.torch_at("robot", a, (0.0, 0.0, 1.0), tuple(d / max(np.linalg.norm(d), 1e-12)))
                c = phys.ctwd_mm() or phys.cfg.stick_out_mm
                i = phys.current_a(w[k], c)
                ctwd.append(c)
                i_set = r.i_min_a + slope * (w[k] - r.wfs_min_m_min)   # the synergic line's current at this feed
                bad += abs(i / i_set - 1.0) > 0.10
                n += 1
                phys.lay("robot", a, b, math.dist(a, b) / v[k] * 60.0, i, w[k])
            phys.end_bead()
        xy = np.concatenate([_along(p.points[:, :2], 1.0) for p in la.passes])
        top = hm.deposit_tops(xy[:, 0], xy[:, 1]) - la.z_mm
        top = top[np.isfinite(top)]
        out.append({"layer": la.index, "spread_mm": float(top.max() - top.min()),
                    "rms_mm": float(np.sqrt(np.mean(top ** 2))), "mean_mm": float(top.mean()),
                    "ctwd_min_mm": float(min(ctwd)), "ctwd_max_mm": float(max(ctwd)),
                    "current_out_share": bad / max(n, 1)})
    return out


def _along(pts: np.ndarray, step: float) -> np.ndarray:
    lens = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.r_[0.0, np.cumsum(lens)]
    s = np.arange(0.0, cum[-1], step)
    return np.column_stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])])


def wall_mesh(length: float, width: float, layers: int, h: float = 0.77) -> Any:
    """A single-bead wall: a box one bead wide, `layers` layers of `h` tall."""
    # lazy: only the wall's path needs it
    import trimesh

    m = trimesh.creation.box(extents=(length, width, layers * h))
    m.apply_translation((length / 2 + 10.0, width / 2 + 10.0, layers * h / 2.0))
    return m


def figures(part: Path, width: float, layers: int | None, material: Material, wall: float = 0.0,
            pour_ff: bool = False) -> dict[str, Any]:
    res: dict[str, Any] = {"part": f"wall {wall:g} mm x {layers} layers" if wall else part.name, "width_mm": width,
                           "model": "pour" if pour_ff else "splat"}
    for ff in (False, True):
        t0 = time.perf_counter()
        c0 = time.process_time()
        if wall:
            job = plan_part(wall_mesh(wall, width, layers or 40),
                            PlanOptions(width_mm=width, perimeters=1, allow_underfill=True, feed_forward=ff,
                                        feed_forward_pour=pour_ff), material)
        else:
            job = plan_part(str(part), PlanOptions(width_mm=width, perimeters="all", feed_forward=ff,
                                                   feed_forward_pour=pour_ff), material)
        plan_s = time.perf_counter() - t0
        plan_cpu_s = time.process_time() - c0
        if layers:
            job = Job(job.source, job.material, job.bead, job.layers[:layers], job.summary, job.schema, job.frame)
        truth = pour(job, material)
        key = "feed_forward" if ff else "plain"
        res[key] = {"plan_s": round(plan_s, 2), "plan_cpu_s": round(plan_cpu_s, 2),
                    "true_spread_mm_max": round(max(t["spread_mm"] for t in truth), 3),
                    "true_spread_mm_last": round(truth[-1]["spread_mm"], 3),
                    "true_rms_mm_max": round(max(t["rms_mm"] for t in truth), 3),
                    "true_top_mean_mm_last": round(truth[-1]["mean_mm"], 3),
                    "ctwd_range_mm": [round(min(t["ctwd_min_mm"] for t in truth), 2),
                                      round(max(t["ctwd_max_mm"] for t in truth), 2)],
                    "current_out_share_max": round(max(t["current_out_share"] for t in truth), 4),
                    "per_layer_true_spread_mm": [round(t["spread_mm"], 3) for t in truth]}
        if ff:
            s = job.summary.get("feed_forward", {})
            res[key]["predicted_spread_before_mm_max"] = s.get("worst_before_mm")
            res[key]["predicted_spread_after_mm_max"] = s.get("worst_after_mm")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", type=Path, default=CONFIG_DIR / "parts" / "square-hole.stl")
    ap.add_argument("--width", type=float, default=7.0)
    ap.add_argument("--layers", type=int, default=None)
    ap.add_argument("--material", default="inconel718-1.0mm")
    ap.add_argument("--wall", type=float, default=0.0, help="a single-bead wall this long (mm; --layers, default 40)")
    ap.add_argument("--pour", action="store_true", help="the poured feed-forward (planner/level_pour.py)")
    a = ap.parse_args()
    print(json.dumps(figures(a.part, a.width, a.layers, load_material(a.material), a.wall, a.pour), indent=1))


if __name__ == "__main__":
    main()

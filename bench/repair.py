"""Hybrid repair end to end on the simulators (issue 17): `python -m bench.repair [--poses N] [--seed S]`.

A 100×100×20 block with a 20×20×4 pocket milled into one corner (the stock) and its nominal CAD;
the stock is mounted with a random pose (tilts up to 2°, rotation up to 5°, offsets up to 5 mm),
`cell repair run --sim` runs the chain, and the deposit log (workpiece frame) is read against the
plan: lateral distance of every deposited segment from the planned beads, its z from the nearest
planned layer, and the verify probe's height error, taken apart per touch (`truth`): the planned
top under the touch, the simulated deposit's true top there (its height map) and the touched z.
`--process-control layer` runs the build closed loop (docs/closed-loop.md).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import trimesh
from shapely.geometry import LineString, Point
from shapely.ops import unary_union

from bench.five_axis import _seg_dist
from controller.job.weld_path import weld_points
from controller.runtime.devices import with_urls
from controller.cli.main import main as cell_main
from controller.harness.repair_parts import make_parts, posed_sim  # noqa: F401  (bench API)
from controller.harness.repair import repair_run_sim
from controller.harness.sim import SimHarness
from controller.job.model import CellJob
from controller.job.read import read_job
from controller.repair import verify_split, verify_targets
from controller.job.repair_volume import to_manifold, to_trimesh
from core.config import load_cell


def worn_parts(tmp: Path, shape: str = "pocket") -> tuple[Path, Path]:
    """The 100×100×20 block (top at z = 0) and its stock with a non-rectangular worn region
    (issue 29): "pocket" (the demo's 20×20×4 corner pocket), "L" (an L of two 8 mm legs, 4 deep,
    around the −X/−Y corner region), "slot" (8 × 30, 3 deep), "edge" (the −Y edge worn away in a
    ramp: 10 mm wide, 3 deep at the edge). Each leaves the middle of the top and +X faces intact."""
    if shape == "pocket":
        return make_parts(tmp)
    cad = trimesh.creation.box(extents=(100, 100, 20))
    cad.apply_translation((0, 0, -10))
    cuts = []
    if shape == "L":
        for ext, ctr in (((30, 8, 4), (-25, -36, -2)), ((8, 30, 4), (-36, -25, -2))):
            b = trimesh.creation.box(extents=ext)
            b.apply_translation(ctr)
            cuts.append(b)
    elif shape == "slot":
        b = trimesh.creation.box(extents=(8, 30, 3))
        b.apply_translation((-30, 25, -1.5))
        cuts.append(b)
    elif shape == "edge":   # a wedge along the -Y edge: 3 mm deep at the edge, 0 at 10 mm in
        v = np.array([[-40, -50.5, 0.5], [10, -50.5, 0.5], [-40, -40, 0.0], [10, -40, 0.0],
                      [-40, -50.5, -3], [10, -50.5, -3], [-40, -40, 0.5], [10, -40, 0.5]], dtype=float)
        cuts.append(trimesh.convex.convex_hull(v))
    else:
        raise ValueError(shape)
    stock = to_manifold(cad, "cad")
    for k, c in enumerate(cuts):
        stock = stock - to_manifold(c, f"cut{k}")
    cad.export(tmp / "cad.stl")
    to_trimesh(stock).export(tmp / "stock.stl")
    return tmp / "cad.stl", tmp / "stock.stl"


def deposit_vs_plan(job: dict, log: Path) -> dict:
    segs = [json.loads(s) for s in (log / "deposit.jsonl").read_text().splitlines()]
    segs = [s for s in segs if s.get("device") == "cnc"]
    A, B = [], []
    for L in job["layers"]:
        for p in L["passes"]:
            pts = np.asarray(weld_points(p["points"], 2.0))
            A.append(pts[:-1])
            B.append(pts[1:])
    a, b = np.vstack(A), np.vstack(B)
    fr = np.array([s["part"]["from"] for s in segs])
    to = np.array([s["part"]["to"] for s in segs])
    # lateral: in xy against the beads of the segment's own layer
    zs = np.array([L["z_mm"] for L in job["layers"]])
    dz = np.abs(np.r_[fr[:, 2], to[:, 2]][:, None] - zs[None, :]).min(axis=1)
    lat = np.maximum(_seg_dist(fr * [1, 1, 0], a * [1, 1, 0], b * [1, 1, 0]),
                     _seg_dist(to * [1, 1, 0], a * [1, 1, 0], b * [1, 1, 0]))
    return {"segments": len(segs), "deposited_mm": round(float(np.linalg.norm(to - fr, axis=1).sum()), 2),
            "planned_mm": round(float(np.linalg.norm(b - a, axis=1).sum()), 2),
            "max_lateral_mm": round(float(lat.max()), 4), "max_dz_mm": round(float(dz.max()), 4)}


async def one(tmp: Path, pose: tuple, scale: float = 60.0, shape: str = "pocket", faults: str = "",
              process_control: str = "open", finish: bool = False) -> dict:
    cad, stock = worn_parts(tmp, shape)
    # the worn edge's ramp rests on the stock and runs out thinner than a bead (tests/repair/test_repair_run.py)
    lax = ["--allow-underfill", "--allow-overhang"] if shape == "edge" else []
    assert cell_main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.3",
                      "--out", str(tmp / "job.json"), *lax]) == 0
    job = json.loads((tmp / "job.json").read_text())
    cell = with_urls(load_cell(), {}, time_scale=scale)
    if process_control != "open":
        cell = cell.model_copy(update={"process_control": cell.process_control.model_copy(update={"mode": process_control})})
    sim = posed_sim(stock, *pose)
    if faults:
        sim = sim.model_copy(update={"faults": faults})
    typed = read_job(tmp / "job.json")
    tops: list[float] = []

    def deposit_tops(harness: SimHarness, rep: dict) -> None:
        # the CNC's height map is in the workpiece frame, the stock's own: the CAD frame
        at = np.asarray(rep["verify"]["at"], dtype=float).reshape(-1, 3)
        tops.extend(harness.world.physics.maps["cnc"].deposit_tops(at[:, 0], at[:, 1]).tolist())

    rep = await repair_run_sim(typed, cell, sim, job_path=tmp / "job.json", runs_dir=tmp / "runs", log_dir=tmp / "log",
                               inspect=deposit_tops, finish=finish)
    return {"pose": pose, "shape": shape, "alignment": rep["alignment"], "verify": rep["verify"],
            "state": rep["state"], "time_scale": rep.get("time_scale"),
            "time_scale_probing": rep.get("time_scale_probing"), "on_deposit": touches_on_deposit(job, rep),
            "truth": per_touch(typed, rep["verify"], tops), **deposit_vs_plan(job, tmp / "log")}


def per_touch(job: CellJob, verify: dict, tops: list[float]) -> dict:
    """The verify's height error taken apart per touch: the planned top under it, the deposit's true
    top there (the simulated height map) and the touched z; `deposit_err` = true top − planned (what
    was built), `probe_err` = touched − true top (what the verify misread)."""
    n = int(verify["points"])
    _, planned, kinds = verify_targets(job, *verify_split(n))
    z = np.asarray(verify["at"], dtype=float)[:, 2]
    top = np.asarray(tops, dtype=float)
    dep, probe = top - planned, z - top
    return {"kinds": kinds, "planned_mm": np.round(planned, 4).tolist(), "deposit_top_mm": np.round(top, 4).tolist(),
            "deposit_err_max_mm": round(float(np.nanmax(np.abs(dep))), 4),
            "deposit_err_mean_mm": round(float(np.nanmean(dep)), 4),
            "probe_err_max_mm": round(float(np.nanmax(np.abs(probe))), 4)}


def touches_on_deposit(job: dict, rep: dict) -> float:
    """Share of the verify touches (CAD frame xy) inside the planned bead footprints of the job."""
    foot = unary_union([LineString([q[:2] for q in p["points"]]).buffer(float(p["width_mm"]) / 2)
                        for L in job["layers"] for p in L["passes"] if len(p["points"]) >= 2])
    pts = rep["verify"].get("at") or []
    return round(sum(1 for q in pts if foot.contains(Point(q[0], q[1]))) / max(len(pts), 1), 4)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--shape", choices=("pocket", "L", "slot", "edge"), default="pocket")
    ap.add_argument("--process-control", choices=("open", "layer"), default="open")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    for _ in range(a.poses):
        pose = (round(float(rng.uniform(-2, 2)), 3), round(float(rng.uniform(-2, 2)), 3),
                round(float(rng.uniform(-5, 5)), 3), tuple(round(float(v), 3) for v in rng.uniform(-5, 5, 3)))
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(asyncio.run(one(Path(tmp), pose, shape=a.shape, process_control=a.process_control))))
    return 0


if __name__ == "__main__":
    sys.exit(main())

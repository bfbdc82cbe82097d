"""Hybrid repair end to end on the simulators (issue 17): `python -m bench.repair [--poses N] [--seed S]`.

A 100×100×20 block with a 20×20×4 pocket milled into one corner (the stock) and its nominal CAD;
the stock is mounted with a random pose (tilts up to 2°, rotation up to 5°, offsets up to 5 mm),
`cell repair run --sim` runs the chain, and the deposit log (workpiece frame) is read against the
plan: lateral distance of every deposited segment from the planned beads, its z from the nearest
planned layer, and the verify probe's height error.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.five_axis import _seg_dist
from controller.motion.weld_path import weld_points
from controller.runtime.devices import with_urls
from controller.cli.main import main as cell_main
from controller.harness.repair_parts import make_parts, posed_sim  # noqa: F401  (bench API)
from controller.harness.repair import repair_run_sim
from core.config import load_cell


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


async def one(tmp: Path, pose: tuple, scale: float = 60.0) -> dict:
    cad, stock = make_parts(tmp)
    assert cell_main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.3",
                      "--out", str(tmp / "job.json")]) == 0
    job = json.loads((tmp / "job.json").read_text())
    cell = with_urls(load_cell(), {}, time_scale=scale)
    rep = await repair_run_sim(job, cell, posed_sim(stock, *pose), job_path=tmp / "job.json",
                               runs_dir=tmp / "runs", log_dir=tmp / "log")
    return {"pose": pose, "alignment": rep["alignment"], "verify": rep["verify"], **deposit_vs_plan(job, tmp / "log")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=3)
    ap.add_argument("--seed", type=int, default=17)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    for _ in range(a.poses):
        pose = (round(float(rng.uniform(-2, 2)), 3), round(float(rng.uniform(-2, 2)), 3),
                round(float(rng.uniform(-5, 5)), 3), tuple(round(float(v), 3) for v in rng.uniform(-5, 5, 3)))
        with tempfile.TemporaryDirectory() as tmp:
            print(json.dumps(asyncio.run(one(Path(tmp), pose))))
    return 0


if __name__ == "__main__":
    sys.exit(main())

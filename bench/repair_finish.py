"""Deposit, machine, verify on seeded repairs (issue 36): `python -m bench.repair_finish [--runs N] [--seed S]`.

Seeded repairs over issue 29's four worn regions (bench/repair.py `worn_parts`: an L, a slot, a worn
ramp edge, a corner pocket), the stock posed up to 2° (tilts, rotation) and 5 mm (offsets), the
hidden process gain (sim.yaml `process.height_gain`) drawn in 0.85–1.15. Each runs `cell repair run
--sim` with finishing (allowance 0.5 mm) and prints one JSON line:
- verify: every touch against CAD (max |z − CAD|, target ±0.05 mm) and its below-CAD figure;
- machined_below_cad_mm: the simulator's height map after machining (its own truth, not the probe)
  over the repaired region, the deepest cell below CAD (target ≤ 0.02 mm);
- shortfall: the deposit's true top before machining below CAD + min_stock anywhere on the
  repaired region (every 0.5 mm cell, its boundary's too; `deposit_min_inner_mm`: cells 1.5 mm in),
  and whether the stock probe stopped the run;
- removal_mean_mm: cut.jsonl's volume over the machined region's area (target ≤ 1 mm);
- loop_late_ms: per phase, the longest the controller's event loop (the one that cycles the CNC
  link) came late to a 10 ms timer: work computed on the loop shows here ("verify" runs on to the
  cell's close and the simulators' stop).
`--keep DIR` keeps each run's files in DIR/run<k>, with the deposit's true top at each stock probe
(stock<round>.npz: xy, top, ctop, repaired).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from bench.repair import worn_parts
from controller.cli.main import main as cell_main
from controller.harness.repair import repair_run_sim
from controller.harness.repair_parts import posed_sim
from controller.job.read import read_job
from controller.runtime.devices import with_urls
from core.config import load_cell
from core.errors import CellError
from planner.finish import cad_top

SHAPES = ("L", "slot", "edge", "pocket")


def _grid(bounds: np.ndarray, step: float = 0.5) -> np.ndarray:
    xs = np.arange(bounds[0, 0] + step / 2, bounds[1, 0], step)
    ys = np.arange(bounds[0, 1] + step / 2, bounds[1, 1], step)
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])


def draw(rng: np.random.Generator) -> tuple[tuple[Any, ...], float]:
    """One repair's pose (tilts, rotation °, offset mm) and hidden gain."""
    pose = (float(rng.uniform(-2, 2)), float(rng.uniform(-2, 2)), float(rng.uniform(-2, 2)),
            tuple(float(v) for v in rng.uniform(-5, 5, 3) * np.array([1, 1, 0.2])))
    return pose, float(rng.uniform(0.85, 1.15))


async def one(tmp: Path, shape: str, pose: tuple[Any, ...], gain: float, keep: bool = False) -> dict[str, Any]:
    cad, stock = worn_parts(tmp, shape)
    lax = ["--allow-underfill", "--allow-overhang"] if shape == "edge" else []
    assert cell_main(["repair", "plan", str(cad), "--stock", str(stock), "--width", "4", "--allowance", "0.5",
                      "--out", str(tmp / "job.json"), *lax]) == 0
    sim = posed_sim(stock, *pose)
    sim = sim.model_copy(update={"process": sim.process.model_copy(update={"height_gain": gain})})
    cell = with_urls(load_cell(), {}, time_scale=60)
    job = read_job(tmp / "job.json")
    cad_m, stock_m = trimesh.load_mesh(str(cad)), trimesh.load_mesh(str(stock))
    rb = np.asarray(job.repair.bounds_mm if job.repair and job.repair.bounds_mm is not None else [[0, 0, 0]] * 2)
    xy = _grid(rb + np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 0.0]]))   # the intact surroundings in: the boundary is seen
    ctop = cad_top(np.asarray(cad_m.triangles), xy)
    repaired = (ctop - np.nan_to_num(cad_top(np.asarray(stock_m.triangles), xy), neginf=-1e9)) > 0.05
    outside = xy[~repaired]
    inner = repaired.copy()
    if len(outside):
        inner &= cKDTree(outside).query(xy)[0] >= 1.5     # the stock probe's inset from the boundary
    truth: dict[str, Any] = {}
    lag: dict[str, float] = {}     # per phase: the longest the controller's loop came late to a 10 ms timer
    now = ["connect"]

    async def watch_loop() -> None:
        while True:
            t = time.monotonic()
            await asyncio.sleep(0.01)
            late = time.monotonic() - t - 0.01
            lag[now[0]] = max(lag.get(now[0], 0.0), late)

    def before_machining(harness: Any, name: str) -> None:
        now[0] = name
        if name == "stock":
            hm = harness.world.physics.maps["cnc"]
            top = hm.solid_tops(xy[:, 0], xy[:, 1])
            top = np.where(np.isfinite(top), top, ctop)
            m = repaired & np.isfinite(ctop)       # every cell of the repaired region, its boundary's too
            k = int(np.argmin(np.where(m, top - ctop, np.inf)))
            truth["deposit_min_over_cad_mm"] = round(float(top[k] - ctop[k]), 4) if m.any() else None
            truth["deposit_min_at"] = [round(float(v), 2) for v in xy[k]]
            mi = inner & np.isfinite(ctop)
            truth["deposit_min_inner_mm"] = round(float(np.min(top[mi] - ctop[mi])), 4) if mi.any() else None
            if keep:   # the deposit's true top at each stock probe, to read after (--keep)
                k = sum(1 for _ in tmp.glob("stock*.npz"))
                np.savez(tmp / f"stock{k}.npz", xy=xy, top=top, ctop=ctop, repaired=repaired)

    out: dict[str, Any] = {"shape": shape, "pose": [round(v, 3) if isinstance(v, float) else [round(x, 3) for x in v]
                                                    for v in pose], "gain": round(gain, 3)}
    t0 = time.time()
    maps: list[Any] = []
    watcher = asyncio.get_running_loop().create_task(watch_loop())
    try:
        rep = await repair_run_sim(job, cell, sim, job_path=tmp / "job.json", runs_dir=tmp / "runs", log_dir=tmp / "log",
                                   on_phase=before_machining, inspect=lambda h, r: maps.append(h.world.physics.maps["cnc"]))
    except CellError as exc:
        out.update(state="stopped", reason=str(exc)[:300], wall_s=round(time.time() - t0, 1), **truth,
                   shortfall_found=True, loop_late_ms={k: round(v * 1000) for k, v in lag.items()})
        return out
    finally:
        watcher.cancel()
    v, mc = rep["verify"], rep["machining"]
    hm = maps[0]
    top = hm.solid_tops(xy[:, 0], xy[:, 1])
    top = np.where(np.isfinite(top), top, ctop)
    m = repaired & np.isfinite(ctop)
    cuts = [json.loads(s) for s in (tmp / "log" / "cut.jsonl").read_text().splitlines()]
    reg = mc["region_mm"]
    area = (reg[2] - reg[0]) * (reg[3] - reg[1])
    min_stock = cell.machining.min_stock_mm
    dmin = truth.get("deposit_min_over_cad_mm")
    out.update(state=rep["state"], wall_s=round(time.time() - t0, 1), stock=rep["stock"]["min_mm"],
               verify_max_mm=v["height_error_max_mm"], verify_below_cad_mm=v["below_cad_max_mm"],
               verify_touches=v["points"], machined_below_cad_mm=round(float(max(0.0, np.max(ctop[m] - top[m]))), 4),
               machined_below_cad_at=[round(float(c), 2) for c in xy[m][int(np.argmax(ctop[m] - top[m]))]],
               machined_above_cad_mm=round(float(np.max(top[m] - ctop[m])), 4),
               removal_mm3=round(sum(c["removed_mm3"] for c in cuts), 1),
               removal_mean_mm=round(sum(c["removed_mm3"] for c in cuts) / area, 3),
               deposit_min_over_cad_mm=dmin, deposit_min_at=truth.get("deposit_min_at"),
               deposit_min_inner_mm=truth.get("deposit_min_inner_mm"), shortfall=bool(dmin is not None and dmin < min_stock),
               shortfall_found=False, time_s=mc["time_s"], redeposits=len(rep["stock"].get("redeposits", [])),
               stock_touches=rep["stock"]["points"], loop_late_ms={k: round(v * 1000) for k, v in lag.items()})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=36)
    ap.add_argument("--shapes", default=",".join(SHAPES))
    ap.add_argument("--only", default="", help="run only these run numbers (e.g. 0-9 or 3,7): the same draws")
    ap.add_argument("--keep", default="", help="keep each run's files (job, runs, logs) in KEEP/run<k> to read after")
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    shapes = a.shapes.split(",")
    only = {int(x) for part in a.only.split(",") if part
            for x in (range(int(part.split("-")[0]), int(part.split("-")[1]) + 1) if "-" in part else [part])}
    for k in range(a.runs):
        pose, gain = draw(rng)
        if only and k not in only:
            continue
        if a.keep:
            d = Path(a.keep) / f"run{k}"
            d.mkdir(parents=True, exist_ok=True)
            print(json.dumps({"run": k, **asyncio.run(one(d, shapes[k % len(shapes)], pose, gain, keep=True))}), flush=True)
            continue
        with tempfile.TemporaryDirectory() as t:
            print(json.dumps({"run": k, **asyncio.run(one(Path(t), shapes[k % len(shapes)], pose, gain))}), flush=True)


if __name__ == "__main__":
    main()

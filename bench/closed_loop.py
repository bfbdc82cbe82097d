"""Closed-loop layer height (issue 27, docs/closed-loop.md): open against closed loop on the
simulated cell, judged from the world's truth (deposit.jsonl's `ctwd_mm`, the height map).

Parts (planned with planner.plan.plan_part from trimesh boxes): a single-bead wall (7 mm bead,
100 mm long; 40 mm for 20 layers or fewer) and a multi-bead block (a perimeter and fill, 40 × 20 mm,
a third of the wall's layers). Hidden process gains
0.85 and 1.15 (sim.yaml `process.height_gain`) plus a temperature term
(`height_temp_coeff`, the part kept hot by a small heat capacity); robot (stick-out through the
arc) and CNC (probe between layers). Figures: final height error (the height map on the last
layer's centre lines, middle part, against the planned top), CTWD range over every bead (the
truth), the through-arc estimate's RMS against the truth per bead, the probe's error against the
height map, and the gain-0.5 pause.

    python -m bench.closed_loop [--quick] [--layers N] [--scale S] [--json FILE]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from controller.api import CellController
from controller.harness.cell import open_cell
from controller.harness.sim import with_urls
from controller.job.model import CellJob
from controller.job.read import job_from_dict
from core.config import load_cell, load_material, load_sim
from planner.job import Layer

MATERIAL = "inconel718-1.0mm"
WIDTH = 7.0


def wall_job(layers: int, length: float = 40.0) -> CellJob:
    """A single-bead wall: a box one bead wide, `layers` planned layers tall."""
    # lazy: only this benchmark's path needs it
    import trimesh

    # lazy: only this benchmark's path needs it
    from planner.job import job_to_dict
    from planner.plan import PlanOptions, plan_part

    mat = load_material(MATERIAL)
    h = 0.77
    m = trimesh.creation.box(extents=(length, WIDTH, layers * h))
    m.apply_translation((0.0, 0.0, layers * h / 2.0))
    return job_from_dict(job_to_dict(plan_part(m, PlanOptions(width_mm=WIDTH, perimeters=1, allow_underfill=True), mat)))


def block_job(layers: int, size: tuple[float, float] = (40.0, 20.0)) -> CellJob:
    """A multi-bead block: perimeters and fill."""
    # lazy: only this benchmark's path needs it
    import trimesh

    # lazy: only this benchmark's path needs it
    from planner.job import job_to_dict
    from planner.plan import PlanOptions, plan_part

    mat = load_material(MATERIAL)
    h = 0.77
    m = trimesh.creation.box(extents=(size[0], size[1], layers * h))
    m.apply_translation((0.0, 0.0, layers * h / 2.0))
    return job_from_dict(job_to_dict(plan_part(m, PlanOptions(width_mm=WIDTH, perimeters=1, allow_underfill=True), mat)))


@dataclass
class Outcome:
    part: str
    platform: str
    gain: float
    temp_coeff: float
    mode: str
    state: str
    layers_planned: int
    layers_built: int
    planned_top_mm: float
    final_top_mm: float | None
    ctwd_min: float | None
    ctwd_max: float | None
    estimate_rms_mm: float | None
    probe_err_max_mm: float | None
    alarms: list[str] = field(default_factory=list)
    records: list[dict] = field(default_factory=list)
    wall_s: float = 0.0
    run_dir: str = ""
    ctwd_all: tuple[float, float] | None = None   # every segment, the beads' ends included

    @property
    def height_error_mm(self) -> float | None:
        return None if self.final_top_mm is None else self.final_top_mm - self.planned_top_mm

    def row(self) -> dict[str, Any]:
        r = lambda x, nd=2: None if x is None else round(x, nd)  # noqa: E731
        return {"part": self.part, "platform": self.platform, "gain": self.gain, "temp_coeff": self.temp_coeff,
                "mode": self.mode, "state": self.state, "layers": f"{self.layers_built}/{self.layers_planned}",
                "height_error_mm": r(self.height_error_mm), "ctwd_min": r(self.ctwd_min), "ctwd_max": r(self.ctwd_max),
                "ctwd_all": [r(v) for v in self.ctwd_all] if self.ctwd_all else None,
                "estimate_rms_mm": r(self.estimate_rms_mm, 3), "probe_err_max_mm": r(self.probe_err_max_mm, 3),
                "alarms": self.alarms[:1], "wall_s": round(self.wall_s, 1)}


def _configs(platform: str, mode: str, scale: float, gain: float, temp_coeff: float, noise_pct: float,
             heat_capacity: float, pc: dict | None = None) -> tuple[Any, Any]:
    cfg = with_urls(load_cell(), {}, time_scale=scale)
    cfg = cfg.model_copy(update={
        "cell": cfg.cell.model_copy(update={"platform": platform}),
        "process_control": cfg.process_control.model_copy(update={"mode": mode, "probe_points": 3, **(pc or {})})})
    sim = load_sim()
    wp = sim.cnc.workpiece.model_copy(update={"tilt_a_deg": 0.0, "tilt_b_deg": 0.0, "rotation_c_deg": 0.0})
    sim = sim.model_copy(update={
        "cnc": sim.cnc.model_copy(update={"workpiece": wp}),
        "thermal": sim.thermal.model_copy(update={"heat_capacity_j_k": heat_capacity}),
        "process": sim.process.model_copy(update={"height_gain": gain, "height_temp_coeff": temp_coeff,
                                                  "height_noise_pct": noise_pct})})
    return cfg, sim


def _segments(log: Path, device: str) -> list[dict]:
    out = []
    p = log / "deposit.jsonl"
    if not p.exists():
        return out
    for line in p.read_text().splitlines():
        d = json.loads(line)
        if d.get("device", device) == device and d.get("ctwd_mm") is not None:
            out.append(d)
    return out


def _final_top(hm: Any, layer: Layer, middle: float = 0.6) -> float | None:
    """Mean of the height map on the layer's centre lines, over the middle of each pass."""
    # lazy: only this benchmark's path needs it
    from controller.align.layer_probe import probe_spots

    spots = probe_spots(layer.passes, 24, middle)
    vals = [hm.surface(x, y) for x, y, _z in spots]
    vals = [v for v in vals if v is not None and math.isfinite(v)]
    return float(np.mean(vals)) if vals else None


def _bead_segments(segs: list[dict], built: list[Layer]) -> dict[tuple[int, int], list[dict]]:
    """The deposited segments of each bead (its layer's commanded z, on its path), in time order."""
    by_z: dict[float, list[dict]] = {}
    for s in segs:
        by_z.setdefault(round(float(s["to"][2]), 3), []).append(s)
    out: dict[tuple[int, int], list[dict]] = {}
    for la, layer in enumerate(built):
        for pa, p in enumerate(layer.passes):
            pts = p.points.tolist()
            out[(la, pa)] = [s for s in by_z.get(round(float(pts[0][2]), 3), []) if _near(s, pts)]
    return out


def bead_ctwd(segs: list[dict], built: list[Layer], middle: float = 0.8) -> list[float]:
    """Each bead's CTWD truth over its middle `middle` share and at least a bead width in from each
    end (the pools at a bead's start and end, where a wall's ends slump: the layer loop levels a
    layer's mean, the path loop its ends), the values of every bead, flattened."""
    vals: list[float] = []
    for (la, pa), mine in _bead_segments(segs, built).items():
        if not mine:
            continue
        lens = np.array([math.dist(s["from"][:2], s["to"][:2]) for s in mine])
        at = np.cumsum(lens) - lens / 2
        cut = max((1.0 - middle) / 2.0 * float(lens.sum()), built[la].passes[pa].width_mm)
        keep = [s["ctwd_mm"] for s, x in zip(mine, at) if cut <= x <= float(lens.sum()) - cut]
        vals += keep or [s["ctwd_mm"] for s in mine]
    return vals


def _estimate_rms(records: list[dict], beads: list[dict], segs: list[dict], built: list[Layer]) -> float | None:
    """Per bead: the through-arc estimate against the truth (mean ctwd_mm of the bead's middle segments)."""
    errs = []
    for b in beads:
        la, pa = b["layer"], b["pass"]
        if la >= len(built):
            continue
        pts = built[la].passes[pa].points.tolist()
        z = pts[0][2]
        mine = [s for s in segs if abs(s["to"][2] - z) < 1e-3 and _near(s, pts)]
        if len(mine) < 3:
            continue
        n = len(mine)
        mid = mine[int(n * 0.2): n - int(n * 0.2)] or mine
        truth = float(np.mean([s["ctwd_mm"] for s in mid]))
        errs.append(b["stick_out_mm"] - truth)
    return float(np.sqrt(np.mean(np.square(errs)))) if errs else None


def _near(seg: dict, pts: list, tol: float = 0.3) -> bool:
    q = np.asarray(seg["to"][:2], dtype=float)
    for a, b in zip(pts, pts[1:]):
        a2, b2 = np.asarray(a[:2], dtype=float), np.asarray(b[:2], dtype=float)
        d = b2 - a2
        t = float(np.clip(np.dot(q - a2, d) / max(float(np.dot(d, d)), 1e-12), 0.0, 1.0))
        if float(np.linalg.norm(a2 + t * d - q)) < tol:
            return True
    return False


async def build(job: CellJob, *, part: str, platform: str, gain: float, mode: str, tmp: Path, scale: float = 60.0,
                temp_coeff: float = 0.0, noise_pct: float = 0.0, heat_capacity: float = 2000.0,
                timeout_s: float = 900.0, pc: dict | None = None) -> Outcome:
    """One build on the simulators; the outcome judged from the world's truth."""
    # lazy: only this benchmark's path needs it
    from controller.job.identity import run_dir_for

    cfg, sim = _configs(platform, mode, scale, gain, temp_coeff, noise_pct, heat_capacity, pc)
    log = run_dir_for(job, tmp / "runs") / "sim"   # where the build record finds the truth
    async with open_cell(cfg, sim=sim, log_dir=log, runs_dir=tmp / "runs", connect=False) as ctl:
        harness = ctl.simulators
        t0 = time.monotonic()
        res, paused = await _run(ctl, job, t0, timeout_s)
        assert ctl.journal is not None and ctl.runner is not None and harness is not None
        rows = ctl.journal.query("SELECT kind, message FROM events WHERE kind IN ('layer', 'stick_out', 'alarm')"
                                 " ORDER BY id")
        built = [ctl.runner.layers.layer(j) for j in range(ctl.runner.layers.layer_count())]
        hm = harness.world.physics.maps.get(platform) if harness.world.physics is not None else None
        run_dir = str(ctl.run_dir)
    records = [json.loads(m) for k, m in rows if k == "layer"]
    beads = [json.loads(m) for k, m in rows if k == "stick_out"]
    segs = _segments(log, platform)
    ctwd = bead_ctwd(segs, built)          # the truth on every bead's steady part
    raw = [s["ctwd_mm"] for s in segs]     # and on every deposited segment, ends included
    return Outcome(part, platform, gain, temp_coeff, mode, ("paused, then " if paused else "") + res.state,
                   len(job.layers), res.layers_done, job.layers[-1].z_mm,
                   _final_top(hm, built[-1]) if hm is not None and built else None,
                   min(ctwd) if ctwd else None, max(ctwd) if ctwd else None,
                   _estimate_rms(records, beads, segs, built) if beads else None,
                   _probe_error(records, hm, built) if platform == "cnc" and hm is not None else None,
                   [m for k, m in rows if k == "alarm"], records, time.monotonic() - t0, run_dir,
                   (min(raw), max(raw)) if raw else None)


async def _run(ctl: CellController, job: CellJob, t0: float, timeout_s: float) -> tuple[Any, bool]:
    """Connect, build; a pause (the control's) ends the build by an abort. (result, paused)."""
    paused = False
    await ctl.connect(reply_timeout_ms=500.0)
    ctl.open_job(job)
    task = asyncio.ensure_future(ctl.start())
    while not task.done():
        await asyncio.sleep(0.05)
        if ctl.machine.state.value == "paused" or time.monotonic() - t0 > timeout_s:
            paused = paused or ctl.machine.state.value == "paused"
            ctl.abort()
    return await task, paused


def _probe_error(records: list[dict], hm: Any, built: list[Layer]) -> float | None:
    """The last probed layer's top against the height map there (same spots, the map's truth)."""
    last = [r for r in records if r.get("source") == "probe"]
    if not last:
        return None
    r = last[-1]
    # lazy: only this benchmark's path needs it
    from controller.align.layer_probe import probe_spots

    spots = probe_spots(built[r["layer"]].passes, 3)
    truth = float(np.mean([hm.surface(x, y) for x, y, _z in spots]))
    return abs(float(r["measured_top_mm"]) - truth)


CASES = [  # part, platform, gain
    ("wall", "robot", 0.85), ("wall", "robot", 1.15), ("wall", "cnc", 0.85), ("wall", "cnc", 1.15),
    ("block", "robot", 0.85), ("block", "robot", 1.15), ("block", "cnc", 0.85), ("block", "cnc", 1.15),
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench.closed_loop")
    ap.add_argument("--quick", action="store_true", help="a 10-layer wall and block, robot and CNC, gain 0.85")
    ap.add_argument("--layers", type=int, default=60, help="wall layers (the block: a third)")
    ap.add_argument("--scale", type=float, default=30.0, help="robot time scale (the through-arc estimate wants "
                    "samples: the power source's 10 ms cycle gives ~6 per wall bead at 30)")
    ap.add_argument("--cnc-scale", type=float, default=60.0)
    ap.add_argument("--temp-coeff", type=float, default=0.002)
    ap.add_argument("--only", default="", help="part:platform[:gain] filter, e.g. wall:robot")
    ap.add_argument("--modes", default="open,layer")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv or [])
    n_wall = 10 if args.quick else args.layers
    # a long wall: its ends slump a little more each layer (a 2.5-D pool running down the end
    # faces), so a short wall 60 layers tall turns into a dome; 100 mm keeps a straight middle
    jobs = {"wall": wall_job(n_wall, 100.0 if n_wall > 20 else 40.0), "block": block_job(max(4, n_wall // 3))}
    cases = [c for c in CASES if not args.quick or c[2] == 0.85]
    if args.only:
        want = args.only.split(":")
        cases = [c for c in cases if all(str(a) == str(b) for a, b in zip(want, c))]
    out = []
    for part, platform, gain in cases:
        for mode in args.modes.split(","):
            for _attempt in range(2):   # a link fault of a loaded host (watchdog) is retried once
                with tempfile.TemporaryDirectory(prefix="closed_loop_") as d:
                    o = asyncio.run(build(jobs[part], part=part, platform=platform, gain=gain, mode=mode, tmp=Path(d),
                                          scale=args.scale if platform == "robot" else args.cnc_scale,
                                          temp_coeff=args.temp_coeff, heat_capacity=150.0))
                if o.state != "fault":
                    break
                print(json.dumps({"retry": o.row()}), flush=True)
            print(json.dumps(o.row()), flush=True)
            out.append(o.row())
    with tempfile.TemporaryDirectory(prefix="closed_loop_") as d:
        o = asyncio.run(build(jobs["wall"], part="wall", platform="robot", gain=0.5, mode="layer", tmp=Path(d),
                              scale=args.scale))
    print(json.dumps({"gain_0.5": o.row(), "alarm": o.alarms[:1]}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

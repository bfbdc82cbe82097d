"""The path loop's controller against the simulated world's physics alone (no devices, no clock):
a fast study of what the law can reach (docs/closed-loop.md "Along the path").

The real control (controller/runtime/layer_control.py's LayerControl, with its path loop and its
journal) lays each pass through sims/process_world.py's ProcessPhysics directly: per segment of
the pass as built, the torch's CTWD is sampled every `--sample-mm` (the power source's 10 ms
cycle at the bench's time scale 10 is about 1.6 mm of bead), the current follows it (the
melting-rate truth on the synergic line, with the material's current ripple), the control gets
each sample at the last point the robot reported reaching (as the runner's `arc_sample` seam
does), and the segment is laid. The figures are bench/path_loop.py's, from the same kind of rows
deposit.jsonl holds. What this leaves out: the real-time stack (the robot's reported positions
arriving late, a segment split at moves, the source's sample timing).

    python -m bench.path_offline [--only wall:0.85] [--layers 40] [--pc JSON]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.closed_loop import MATERIAL, wall_job
from bench.path_loop import END_SAG, PC, REGION_GAIN, RUN_IN_MM, beads_of, demo_job, final_top, judge_beads, layer_rms, quarter_box
from controller.job.model import CellJob
from controller.journal.store import Journal
from controller.runtime.build import WorkItem
from controller.runtime.layer_control import LayerControl
from core.config import ProcessControl, ProcessSim, SimRegion, load_cell, load_material
from core.melting import synergic_current
from sims.process_world import ProcessPhysics


def lay_pass(phys: ProcessPhysics, p: Any, noise: np.random.Generator, sample_mm: float, ripple: float,
             on_sample: Any) -> tuple[list[dict[str, Any]], list[float]]:
    """One bead: its deposit rows (deposit.jsonl's fields) and its arc-stable current samples."""
    mat = phys.material
    phys.new_bead()
    pts, speeds, wfs = p.points, p.speeds(), p.wire_feeds()
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts[:, :2], axis=0).T))])
    rows: list[dict[str, Any]] = []
    currents: list[float] = []
    carry = 0.0
    t = 0.0
    for j in range(len(pts) - 1):
        q0, q1 = pts[j], pts[j + 1]
        seg = float(cum[j + 1] - cum[j])
        if seg <= 1e-9:
            continue
        syn = synergic_current(mat.ribeiro, float(wfs[j]))
        d = (float(q1[0] - q0[0]), float(q1[1] - q0[1]), float(q1[2] - q0[2]))
        cts, cur = [], []
        s = carry
        while s < seg:
            q = q0 + (q1 - q0) * (s / seg)
            phys.torch_at("robot", (float(q[0]), float(q[1]), float(q[2])), (0.0, 0.0, 1.0), d)
            c = phys.ctwd_mm()
            assert c is not None
            i = phys.current_a(float(wfs[j]), c, syn) * (1.0 + ripple * float(noise.standard_normal()))
            cts.append(c)
            cur.append(i)
            on_sample(float(cum[j]), i)
            s += sample_mm
        carry = s - seg
        if not cts:   # a segment shorter than the sampling: its end's CTWD
            phys.torch_at("robot", (float(q1[0]), float(q1[1]), float(q1[2])), (0.0, 0.0, 1.0), d)
            c = phys.ctwd_mm()
            assert c is not None
            cts, cur = [c], [phys.current_a(float(wfs[j]), c, syn)]
        dur = seg / float(speeds[j]) * 60.0
        im = float(np.mean(cur))
        phys.lay("robot", tuple(map(float, q0)), tuple(map(float, q1)), dur, im, float(wfs[j]), 20.0)
        currents += cur
        rows.append({"from": [float(v) for v in q0], "to": [float(v) for v in q1], "t0": t, "t1": t + dur,
                     "current_a": im, "ctwd_mm": float(np.mean(cts)), "wfs_m_min": float(wfs[j]),
                     "planned_a": syn, "device": "robot"})
        t += dur
    phys.end_bead()
    return rows, currents


async def build(job: CellJob, *, gain: float, pc: dict[str, Any], tmp: Path, disturbed: bool = True,
                sample_mm: float = 1.6, seed: int = 1, leave_out: str = "") -> tuple[dict[str, Any], list[Any]]:
    """One build; `leave_out`: disturbances left out of the world (region, runin, sag), to see each one's share."""
    mat = load_material(MATERIAL)
    on = {k: disturbed and k not in leave_out for k in ("region", "runin", "sag")}
    regions = (SimRegion(box_mm=quarter_box(job), height_gain=REGION_GAIN),) if on["region"] else ()
    phys = ProcessPhysics(mat, ProcessSim(height_gain=gain, regions=regions,
                                          start_run_in_mm=RUN_IN_MM if on["runin"] else 0.0,
                                          end_sag=END_SAG if on["sag"] else 0.0))
    cfg = load_cell().process_control.model_copy(update={"mode": "path", **pc})
    cfg = ProcessControl.model_validate(cfg.model_dump())
    lc = LayerControl(job=job, cfg=cfg, material=mat, platform="robot", journal=Journal(tmp / "journal.sqlite"))
    work = [WorkItem(la, pa) for la in range(len(job.layers)) for pa in range(len(job.layers[la].passes))]
    noise = np.random.default_rng(seed)
    ripple = mat.melting.current_noise_pct / 100.0
    rows: list[dict[str, Any]] = []
    pauses: list[str] = []
    t0 = time.monotonic()
    while work:
        item, work = work[0], work[1:]
        p = lc.pass_for(item.layer, item.pass_)
        got, currents = lay_pass(phys, p, noise, sample_mm, ripple,
                                 lambda s, i, la=item.layer, pa=item.pass_: lc.arc_sample(la, pa, s, i))
        rows += got
        lc.bead_closed(item.layer, item.pass_, currents, p.wfs_m_min)
        after = await lc.after_pass(item, work)
        if after.pause:
            pauses.append(after.pause)
        if after.rest is not None:
            work = list(after.rest)
    out = figures(lc, job, rows, phys, pauses)
    out["wall_s"] = round(time.monotonic() - t0, 1)
    return out, layer_rms(beads_of(rows), _planned(lc))


def _planned(lc: LayerControl) -> dict[float, float]:
    return {round(float(r["z_mm"]), 3): float(r["planned_top_mm"]) for r in lc.records if r.get("z_mm") is not None}


def seg_plan_dev(beads: list[list[dict[str, Any]]], width: float = 7.0) -> float:
    """The largest deviation of a segment's current from its own plan (its commanded wire feed on
    the synergic line) over every bead's steady part (a bead width in from each end)."""
    dev = 0.0
    for b in beads:
        lens = np.array([math.dist(s["from"][:2], s["to"][:2]) for s in b])
        sc = np.cumsum(lens) - lens / 2
        for s, x in zip(b, sc):
            if width < x < lens.sum() - width:
                dev = max(dev, abs(s["current_a"] / s["planned_a"] - 1.0))
    return dev


def figures(lc: LayerControl, job: CellJob, rows: list[dict[str, Any]], phys: ProcessPhysics,
            pauses: list[str]) -> dict[str, Any]:
    """bench/path_loop.py's figures from the world's truth."""
    built = [lc.layer(j) for j in range(lc.n_total)]
    beads = beads_of(rows)
    rms = layer_rms(beads, _planned(lc))
    after5 = rms[5:]
    out: dict[str, Any] = {"layers": f"{lc.n_total}/{len(job.layers)}", "pauses": len(pauses),
                           "first_pause": pauses[0][:160] if pauses else None}
    out.update(final_top(phys.maps["robot"], built[-1], job.layers[-1].z_mm))
    if after5:
        out.update(rms_after5_max_mm=round(max(r[1] for r in after5), 3),
                   rms_after5_mean_mm=round(float(np.mean([r[1] for r in after5])), 3),
                   err_after5_max_mm=round(max(r[2] for r in after5), 3))
    current = float(np.mean([p.current_a for la in job.layers for p in la.passes]))
    out.update(judge_beads(beads, current, 7.0))
    out["current_dev_seg_plan_pct"] = round(100 * seg_plan_dev(beads), 2)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench.path_offline")
    ap.add_argument("--layers", type=int, default=40)
    ap.add_argument("--length", type=float, default=100.0)
    ap.add_argument("--demo-layers", type=int, default=0)
    ap.add_argument("--only", default="")
    ap.add_argument("--undisturbed", action="store_true")
    ap.add_argument("--leave-out", default="", help="disturbances left out: region,runin,sag")
    ap.add_argument("--pc", default="")
    ap.add_argument("--rms", action="store_true", help="print the per-layer RMS too")
    args = ap.parse_args(argv or [])
    cases = [("wall", 0.85), ("wall", 1.15), ("demo", 0.85), ("demo", 1.15)]
    if args.only:
        want = args.only.split(":")
        cases = [c for c in cases if all(str(a) == str(b) for a, b in zip(want, c))]
    for part, gain in cases:
        job = wall_job(args.layers, args.length) if part == "wall" else demo_job(args.demo_layers or None)
        with tempfile.TemporaryDirectory(prefix="path_offline_") as d:
            o, rms = asyncio.run(build(job, gain=gain, pc={**PC, **json.loads(args.pc or "{}")}, tmp=Path(d),
                                       disturbed=not args.undisturbed, leave_out=args.leave_out))
        print(json.dumps({"part": part, "gain": gain, **o}), flush=True)
        if args.rms:
            print(" ".join(f"{z:.1f}:{r:.2f}/{m:.2f}" for z, r, m in rms), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""5-axis deposition on the CNC simulator: plan a part 5-axis, build it, read the deposit log back.

`python -m bench.five_axis [--part tube|frustum] [--table AB|AC] [--scale S] [--host-line-ms MS]` prints
the figures of issue 18: per deposited segment the distance from the plan in the workpiece frame, the tool-axis
error, the tool-tip speed error, and the largest rotary step against the planned axis change.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from controller.job.weld_path import weld_points, weld_segments
from controller.harness.cell import open_cell
from controller.harness.sim import with_urls
from controller.job.read import job_from_dict
from core.config import load_cell, load_material, load_sim
from controller.motion.post5 import weld_axes
from planner.five_axis import FiveAxisOptions
from planner.job import job_to_dict
from planner.plan import PlanOptions, plan_part
from controller.defaults import SIM_REPLY_TIMEOUT_MS



def plan5(mesh, width: float = 3.0, five: bool = True) -> dict:
    mat = load_material("inconel718-1.0mm")
    job = plan_part(mesh, PlanOptions(width_mm=width, five_axis=FiveAxisOptions() if five else None), mat)
    return job_to_dict(job)


# A 5-axis CNC runs grblHAL (grbl 1.1h has three axes): its RX ring is 1024 bytes (`$I`
# `[OPT:…,100,1024]`; real grblHAL reports `Bf:100,1023` idle), and the shipped 5-axis cell
# (config/cell-grblhal5.yaml) says so. With grbl 1.1h's 128 bytes only two or three 5-axis lines
# are in flight, and at time scale 10 (a line every 1.1 ms of wall time) the link starves on the
# round trips alone (docs/controller.md).
GRBLHAL_RX_BYTES = 1024
GRBLHAL5_CELL = Path(__file__).resolve().parent.parent / "config" / "cell-grblhal5.yaml"


def kin_cfg(table: str, rx_buffer_bytes: int = GRBLHAL_RX_BYTES):
    """The shipped 5-axis cell (its A/B table), or its A/C variant; `rx_buffer_bytes` to try another ring."""
    cfg = load_cell(GRBLHAL5_CELL)
    cnc = cfg.devices.cnc.model_copy(update={"rx_buffer_bytes": rx_buffer_bytes})
    cfg = cfg.model_copy(update={"devices": cfg.devices.model_copy(update={"cnc": cnc})})
    if table == "AC":
        kin = cfg.kinematics.model_copy(update={"table": "AC", "axis_second": (0.0, 0.0, 1.0),
                                                "pivot_mm": (0.0, 0.0, 30.0), "offset_mm": (0.0, 0.0, 10.0)})
        cfg = cfg.model_copy(update={"kinematics": kin})
    return cfg


def level_sim():
    """The simulator's workpiece clamped square (the job's part frame is the workpiece frame)."""
    sim = load_sim()
    wp = sim.cnc.workpiece.model_copy(update={"tilt_a_deg": 0.0, "tilt_b_deg": 0.0, "rotation_c_deg": 0.0})
    return sim.model_copy(update={"cnc": sim.cnc.model_copy(update={"workpiece": wp})})


async def build(job: dict, tmp: Path, table: str = "AB", scale: float = 60.0,
                beside: bool = False, rx_buffer_bytes: int = GRBLHAL_RX_BYTES) -> tuple[object, Path]:
    """Build `job` on the simulated CNC at `scale`, lowered to what the link can feed (issue 29)."""
    # lazy: only this benchmark's path needs it
    from controller.motion.cnc5 import limit_time_scale

    typed = job_from_dict(job)   # the job file's object, read as `cell run` reads it
    cfg, _note = limit_time_scale(with_urls(kin_cfg(table, rx_buffer_bytes), {}, time_scale=scale), typed, beside=beside)
    log = tmp / "log"
    if beside:
        # `cell sim up` in a process of its own (the demo's topology): the simulators' deposit
        # computation and Modbus answers no longer share this interpreter's lock
        # lazy: only this benchmark's path needs it
        import yaml

        sim_yaml = tmp / "level-sim.yaml"
        sim_yaml.write_text(yaml.safe_dump(level_sim().model_dump(mode="json")))
        async with open_cell(cfg, sim=True, process=True, sim_config=sim_yaml, log_dir=log,
                             runs_dir=tmp / "runs") as ctl:
            ctl.open_job(typed)
            cpu0, wall0 = time.process_time(), time.perf_counter()
            res = await ctl.start()
            _COST.update(cpu_s=time.process_time() - cpu0, wall_s=time.perf_counter() - wall0)
        return res, log
    async with open_cell(cfg, sim=level_sim(), log_dir=log, runs_dir=tmp / "runs",
                         reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        ctl.open_job(typed)
        cpu0, wall0 = time.process_time(), time.perf_counter()
        res = await ctl.start()
        _COST.update(cpu_s=time.process_time() - cpu0, wall_s=time.perf_counter() - wall0)
    return res, log


# this process's CPU and wall seconds over the last `build` (the controller's share with --beside)
_COST: dict[str, float] = {}


def line_cost(log: Path) -> dict:
    """The controller's CPU per line streamed to the CNC (cnc.jsonl's lines) over the build."""
    n = sum(1 for s in (log / "cnc.jsonl").read_text().splitlines() if json.loads(s).get("line"))
    if not _COST or n == 0:
        return {}
    return {"cnc_lines": n, "build_wall_s": round(_COST["wall_s"], 2), "build_cpu_s": round(_COST["cpu_s"], 2),
            "cpu_ms_per_line": round(_COST["cpu_s"] / n * 1000.0, 3)}


def _seg_dist(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of each query point to the nearest of the segments a→b."""
    ab = b - a
    L2 = np.maximum((ab * ab).sum(axis=1), 1e-12)
    out = np.empty(len(q))
    for i, p in enumerate(q):
        t = np.clip(((p - a) * ab).sum(axis=1) / L2, 0, 1)
        out[i] = np.sqrt((((a + t[:, None] * ab) - p) ** 2).sum(axis=1)).min()
    return out


def _axis_err(ax_log: np.ndarray, allax: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Degrees between each executed tool axis and the planned axis interpolated between the two
    planned weld points nearest to it (a move split for the chord tolerance lies between them)."""
    two = np.argsort(d2, axis=1)[:, :2]
    a1, a2 = allax[two[:, 0]], allax[two[:, 1]]
    best = np.full(len(ax_log), np.inf)
    for f in np.linspace(0.0, 1.0, 21):
        ax = (1.0 - f) * a1 + f * a2
        ax /= np.maximum(np.linalg.norm(ax, axis=1, keepdims=True), 1e-12)
        best = np.minimum(best, np.degrees(np.arccos(np.clip((ax_log * ax).sum(axis=1), -1, 1))))
    return best


def figures(job: dict, log: Path, max_step_mm: float = 2.0) -> dict:
    """Deposit log (workpiece frame) against the plan, and the executed rotary steps."""
    segs = [json.loads(s) for s in (log / "deposit.jsonl").read_text().splitlines()]
    segs = [s for s in segs if s.get("device") == "cnc"]
    A, B, AX, SP, PAX = [], [], [], [], []
    for la in job["layers"]:
        for p in la["passes"]:
            pts = np.asarray(weld_points(p["points"], max_step_mm))
            axes = np.asarray(weld_axes(p["points"], p.get("axes"), max_step_mm))
            A.append(pts[:-1])
            B.append(pts[1:])
            AX.append(axes)
            PAX.append(pts)
            sp = np.atleast_1d(np.asarray(p["speed_mm_min"], dtype=float))   # one, or one per segment (cell-job/2)
            seg = np.asarray(weld_segments(p["points"], max_step_mm))
            SP.append(np.r_[sp[np.minimum(seg, len(sp) - 1)], sp[-1]] if len(sp) > 1 else np.full(len(pts), sp[0]))
    a, b = np.vstack(A), np.vstack(B)
    allpts, allax, allsp = np.vstack(PAX), np.vstack(AX), np.concatenate(SP)
    fr = np.array([s["part"]["from"] for s in segs])
    to = np.array([s["part"]["to"] for s in segs])
    mid = 0.5 * (fr + to)
    dev = np.maximum.reduce([_seg_dist(fr, a, b), _seg_dist(to, a, b), _seg_dist(mid, a, b)])
    d2 = ((to[:, None, :] - allpts[None, :, :]) ** 2).sum(axis=2)
    near = np.argmin(d2, axis=1)
    ax_log = np.array([s["axis"] for s in segs])
    ax_err = _axis_err(ax_log, allax, d2)
    length = np.linalg.norm(to - fr, axis=1)
    dt = np.array([s["t1"] - s["t0"] for s in segs])
    ok = length >= 0.5  # the log rounds t to 0.1 ms: shorter stretches cannot show 2 %
    speed = length[ok] / dt[ok] * 60.0
    # per-segment speeds (cell-job/2): a deposit stretch is judged against the planned speeds
    # between its two ends (the range of the planned points nearest to each)
    near0 = np.argmin(((fr[:, None, :] - allpts[None, :, :]) ** 2).sum(axis=2), axis=1)
    lo = np.array([allsp[min(a, b):max(a, b) + 1].min() for a, b in zip(near0, near)])[ok]
    hi = np.array([allsp[min(a, b):max(a, b) + 1].max() for a, b in zip(near0, near)])[ok]
    sp_err = np.maximum(np.maximum(lo / speed - 1.0, speed / hi - 1.0), 0.0)
    steps = _rotary_steps(log)
    return {"segments": len(segs), "deposited_mm": round(float(length.sum()), 2),
            "planned_mm": round(float(np.linalg.norm(b - a, axis=1).sum()), 2),
            "max_dev_mm": round(float(dev.max()), 4), "max_axis_err_deg": round(float(ax_err.max()), 3),
            "speed_segments": int(ok.sum()), "max_speed_err": round(float(sp_err.max()), 4),
            "max_rotary_step_deg": steps, "max_planned_axis_step_deg": round(_planned_axis_step(AX), 3)}


def _planned_axis_step(axes_per_pass: list[np.ndarray]) -> float:
    m = 0.0
    for ax in axes_per_pass:
        if len(ax) > 1:
            c = np.clip((ax[1:] * ax[:-1]).sum(axis=1), -1, 1)
            m = max(m, float(np.degrees(np.arccos(c)).max()))
    return m


def _rotary_steps(log: Path) -> float:
    """Largest change of a rotary axis between consecutive G93 weld moves in cnc.jsonl (axis words
    are modal: a line may leave out an axis that does not move)."""
    prev: dict[str, float] | None = None
    pos: dict[str, float] = {}
    worst = 0.0
    for line in (log / "cnc.jsonl").read_text().splitlines():
        g = json.loads(line).get("line", "").replace(" ", "")
        words = {k: float(v) for k, v in re.findall(r"([ABC])(-?\d+\.\d+)", g)}
        pos.update(words)
        if not g.startswith("G1") or "F" not in g or not any(c in g for c in "XYZABC"):
            prev = None if g.startswith("G0") else prev  # a new pass starts after its approach
            continue
        if prev is not None:
            worst = max([worst] + [abs(pos[k] - prev[k]) for k in pos if k in prev])
        prev = dict(pos)
    return round(worst, 3)


def executed_moves(log: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The G93 weld moves the CNC simulator executed (cnc.jsonl): (from, to) machine X Y Z A S."""
    pos = np.zeros(5)
    letters = "XYZ"
    inverse, out = False, []
    for line in (log / "cnc.jsonl").read_text().splitlines():
        g = json.loads(line).get("line", "").replace(" ", "").upper()
        if "G93" in g:
            inverse = True
        if "G94" in g:
            inverse = False
        words = dict(re.findall(r"([XYZABC])(-?\d+\.?\d*)", g))
        if not words or not g.startswith(("G0", "G1")):
            continue
        new = pos.copy()
        for c, v in words.items():
            if c in "XYZ":
                new[letters.index(c)] = float(v)
            elif c == "A":
                new[3] = float(v)
            else:
                new[4] = float(v)
        if inverse and g.startswith("G1"):
            out.append((pos.copy(), new.copy()))
        pos = new
    return out


def executed_mid_dev(job: dict, log: Path, table: str, max_step_mm: float = 2.0) -> dict:
    """Issue 29: the middle (and quarter points) of every executed 5-axis move, through the table's
    forward kinematics, against the planned path (the job's weld segments, workpiece frame)."""
    # lazy: only this benchmark's path needs it
    from controller.motion.kinematics import Trunnion
    from controller.motion.post5 import tip_path

    tr = Trunnion.from_config(kin_cfg(table).kinematics)
    A, B = [], []
    for la in job["layers"]:
        for p in la["passes"]:
            pts = np.asarray(weld_points(p["points"], max_step_mm))
            A.append(pts[:-1])
            B.append(pts[1:])
    a, b = np.vstack(A), np.vstack(B)
    moves = executed_moves(log)
    mids = np.array([tip_path(tr, m0, m1, (0.5,))[0] for m0, m1 in moves])
    quarters = np.array([q for m0, m1 in moves for q in tip_path(tr, m0, m1, (0.25, 0.75))])
    dm, dq = _seg_dist(mids, a, b), _seg_dist(quarters, a, b)
    return {"moves": len(moves), "max_mid_dev_mm": round(float(dm.max()), 4),
            "max_quarter_dev_mm": round(float(dq.max()), 4)}


def export_mid_dev(job: dict, table: str, baud: int = 115200) -> dict:
    """Issue 38: `cell export --format gcode` of the job, read back: the middle (and quarter
    points) of every G93 line through the table's forward kinematics against the planned path,
    and each line's time against twice its serial time at `baud`."""
    # lazy: only this benchmark's path needs it
    from controller.export import build_program
    from controller.export.gcode import parse_gcode, write_gcode
    from controller.motion.kinematics import Trunnion
    from controller.motion.lines5 import part_points

    tr = Trunnion.from_config(kin_cfg(table).kinematics)
    prog = build_program(job_from_dict(job), name="bench")
    lines = write_gcode(prog, clearance_mm=10.0, travel_mm_min=3000.0, power_s=1000, trunnion=tr, baud=baud)
    worst = {0.5: 0.0, 0.25: 0.0}
    short, n = 0, 0
    serial = {ln: (len(ln) + 1) * 10.0 / baud for ln in lines}
    g93 = [ln for ln in lines if ln.startswith("G1") and " F" in ln and not ln.startswith("G1 Z")]
    for g, pp in zip(parse_gcode(lines), (p for la in job["layers"] for p in la["passes"])):
        pts = np.asarray(pp["points"])
        rows = np.column_stack([g.points, g.rotary])
        for f in worst:
            q = part_points(tr, np.vstack([rows[:-1] + (rows[1:] - rows[:-1]) * x for x in (f, 1.0 - f)]))
            worst[f] = max(worst[f], float(_seg_dist(q, pts[:-1], pts[1:]).max()))
        n += len(g.feeds)
    for ln in g93:
        f = float(ln.rsplit("F", 1)[1])
        short += 60.0 / f < 2.0 * serial[ln] - 1e-9
    return {"export_lines": n, "export_max_mid_dev_mm": round(worst[0.5], 4),
            "export_max_quarter_dev_mm": round(worst[0.25], 4), "export_lines_under_2x_serial": int(short)}


def bead_gaps(log: Path, device: str = "cnc") -> dict:
    """Issue 29: the torch standing still with the process on — gaps (process time) between
    consecutive deposited segments of one bead (one ends where the next starts) in deposit.jsonl."""
    # lazy: only this benchmark's path needs it
    import math

    segs = [json.loads(s) for s in (log / "deposit.jsonl").read_text().splitlines()]
    segs = [s for s in segs if s.get("device") == device]
    gaps = [b["t0"] - a["t1"] for a, b in zip(segs, segs[1:])
            if math.dist(a.get("part", a)["to"], b.get("part", b)["from"]) < 1e-3]
    g = np.asarray(gaps or [0.0])
    moving = sum(s["t1"] - s["t0"] for s in segs)
    return {"segments": len(segs), "moving_s": round(moving, 3), "still_s": round(float(g.clip(0).sum()), 3),
            "max_gap_s": round(float(g.max()), 4), "gaps_over_10ms": int((g > 0.01).sum())}


def feed_scale(job: dict, table: str, scale: float, beside: bool = False) -> float:
    """The time scale `build` runs `job` at (the asked one, or what the CNC link can feed)."""
    # lazy: only this benchmark's path needs it
    from controller.motion.cnc5 import limit_time_scale

    cfg = with_urls(kin_cfg(table), {}, time_scale=scale)
    return float(limit_time_scale(cfg, job_from_dict(job), beside=beside)[0].cell.time_scale)


def main(argv: list[str] | None = None) -> int:
    # lazy: only this benchmark's path needs it
    from bench.parts5 import cone_frustum, tilted_tube

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("tube", "frustum"), default="tube")
    ap.add_argument("--table", choices=("AB", "AC"), default="AB")
    ap.add_argument("--scale", type=float, default=60.0)
    ap.add_argument("--slow", type=float, default=1.0, help="divide the planned travel speeds by this")
    ap.add_argument("--host-line-ms", type=float, default=None,
                    help="the wall time a streamed line is taken to cost (controller/motion/cnc5.py "
                         "HOST_LINE_WALL_S, HOST_LINE_BESIDE_S with --beside): lower it to build at a scale the feed limit would lower, and "
                         "read the stand-still in still_s (issue 38)")
    ap.add_argument("--rx-bytes", type=int, default=GRBLHAL_RX_BYTES,
                    help="the CNC's RX ring (cell.yaml devices.cnc.rx_buffer_bytes; the simulator has the same): "
                         "grblHAL 1024, grbl 1.1h 128")
    ap.add_argument("--beside", action="store_true",
                    help="run the simulators in `cell sim up` beside this process (the demo's topology)")
    a = ap.parse_args(argv)
    if a.host_line_ms is not None:
        # lazy: only this benchmark's path needs it
        import controller.motion.cnc5 as cnc5

        cnc5.HOST_LINE_WALL_S = cnc5.HOST_LINE_BESIDE_S = a.host_line_ms / 1000.0
    mesh = tilted_tube() if a.part == "tube" else cone_frustum()
    job = plan5(mesh)
    for la in job["layers"]:
        for p in la["passes"]:
            p["speed_mm_min"] = np.divide(p["speed_mm_min"], a.slow).tolist()
    with tempfile.TemporaryDirectory() as tmp:
        res, log = asyncio.run(build(job, Path(tmp), a.table, a.scale, a.beside, a.rx_bytes))
        fig = figures(job, log)
        fig.update(executed_mid_dev(job, log, a.table))
        fig.update(bead_gaps(log))
        fig.update(line_cost(log))
    fig.update({"part": a.part, "table": a.table, "state": getattr(res, "state", None), "beside": a.beside,
                "rx_bytes": a.rx_bytes,
                "time_scale": feed_scale(job, a.table, a.scale, a.beside),
                "passes_done": getattr(res, "passes_done", None)})
    print(json.dumps(fig))
    return 0


if __name__ == "__main__":
    sys.exit(main())

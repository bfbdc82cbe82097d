"""Controller overhead: does it keep a robot's queue full with 1 mm moves at 1,500 mm/min on a
115200-baud link? Runs single long beads against `cell sim up` (a separate process, as real
hardware would be) at increasing time scales (1 = the real case; higher scales shorten the
moves in wall time until the link or the controller cannot keep up) and reports, per scale,
from the robot simulator's own execution log: the times its queue ran dry inside the bead and
the worst lateness of a move; and from the host: the fewest moves it had ahead of the robot,
the controller process's CPU per move (including its 10 ms bus cycles), the wall time per move
(40 ms at scale 1; a 115200-baud frame of ~52 bytes takes 4.5 ms).

    .venv/bin/python -m bench.controller_overhead [--quick]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SPEED = 1500.0   # mm/min
STEP = 1.0       # mm per move


def zigzag_job(length_mm: float) -> dict:
    """One layer, one bead: a zigzag of 50 mm legs, `length_mm` long."""
    pts, y, x = [[0.0, 0.0, 1.0]], 0.0, 0.0
    while len(pts) * 50 < length_mm:
        x = 50.0 - x
        pts.append([x, y, 1.0])
        y += 4.0
        pts.append([x, y, 1.0])
    return {"schema": "cell-job/1", "source": {"file": "zigzag.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.7, "model": "tangent"},
            "layers": [{"index": 0, "z_mm": 1.0, "height_mm": 1.0, "passes": [
                {"role": "infill", "width_mm": 5, "current_a": 120, "speed_mm_min": SPEED, "wfs_m_min": 5.5,
                 "points": pts}]}], "summary": {}}


def robot_starvation(log: Path) -> tuple[int, int, float]:
    """From the robot's own execution log: (weld moves, times the queue ran dry inside the bead,
    worst gap in ms of process time beyond the move's own duration)."""
    recs = [json.loads(x) for x in log.read_text().splitlines() if x.strip()]
    movl = [r for r in recs if r["verb"] == "MOVL"]
    dry, worst = 0, 0.0
    for a, b in zip(movl, movl[1:]):
        if b["seq"] != a["seq"] + 1:
            continue  # a new bead
        need = sum((p - q) ** 2 for p, q in zip(a["target"], b["target"])) ** 0.5 / (SPEED / 60.0)
        late = (b["t"] - a["t"]) - need
        worst = max(worst, late)
        if late > 0.25 * need + 0.002:
            dry += 1
    return len(movl), dry, worst * 1000


async def one(scale: float, length: float, runs: Path, log: Path) -> dict:
    """One bead on a cell whose simulators run in `cell sim up`, a process of their own
    (controller/harness/cell.py `open_cell(process=True)`), logs in `log`."""
    # lazy: only this benchmark's path needs it
    from controller.api import BuildOptions
    from controller.harness.cell import open_cell
    from controller.job.read import job_from_dict
    from core.config import load_cell

    cfg = load_cell()
    cfg = cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"time_scale": scale})})
    async with open_cell(cfg, sim=True, process=True, log_dir=log, runs_dir=runs, connect=False) as ctl:
        ctl.options = BuildOptions(**{**ctl.options.__dict__, "max_step_mm": STEP})
        await ctl.connect()
        job = zigzag_job(length)
        job["source"]["file"] = f"zigzag-x{scale:g}.stl"
        ctl.open_job(job_from_dict(job))
        cpu0, t0 = time.process_time(), time.monotonic()
        res = await ctl.start()
        cpu, wall = time.process_time() - cpu0, time.monotonic() - t0
        ex = ctl.executor
        moves = ex.exec_count
        stats = ctl.devices.robot.stats
    return {"time_scale": scale, "state": res.state, "moves": moves,
            "move_wall_ms": round(STEP / (SPEED / 60.0) / scale * 1000, 2),
            "host_saw_queue_empty": ex.starved, "min_moves_ahead_host": ex.min_ahead,
            "controller_cpu_ms_per_move_incl_bus": round(cpu / max(moves, 1) * 1000, 3),
            "wall_s": round(wall, 2), "naks": getattr(stats, "naks", None)}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.controller_overhead")
    ap.add_argument("--quick", action="store_true", help="scale 1 and 4 only, short beads")
    a = ap.parse_args(argv)
    scales = [1.0, 4.0] if a.quick else [1.0, 2.0, 4.0, 8.0, 16.0]
    work = Path(tempfile.mkdtemp(prefix="overhead-"))
    ok = True
    for scale in scales:
        log = work / f"log-{scale:g}"
        # ~12 s of bead at every scale (longer in wall time at low scales is not needed)
        length = (150.0 if a.quick else 300.0) * min(scale, 4.0)
        fig = asyncio.run(one(scale, length, work / "runs", log))
        n, dry, worst = robot_starvation(log / "robot.jsonl")
        fig.update({"robot_weld_moves": n, "robot_queue_dry_in_bead": dry, "worst_late_ms_process": round(worst, 2)})
        print(json.dumps(fig), flush=True)
        if scale == 1.0:
            ok = fig["state"] == "complete" and dry == 0
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

"""How fast this host streams 5-axis lines to the CNC simulator, alone (issue 38 item 5).

    .venv/bin/python -m bench.stream5 [--scale 10] [--passes 8] [--part tube|frustum]

The executor's lines for the first passes of bench/five_axis.py's part on the A/B table (approach,
`M3`, the G93 weld lines, `M5`) go through CncLink to the CNC simulator run as a build runs it (its
own thread and precise loop, real-time priorities where the host grants them), at the time
scale, with the arc off and no other device. Figures per weld line: wall time, CPU time of the
process and time its threads waited to run (schedstat), and the stand-still the simulator's own
log shows: the time between one weld block's end and the next's, less the next's own duration.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench.five_axis import kin_cfg, level_sim, plan5  # noqa: E402
from bench.parts5 import cone_frustum, tilted_tube  # noqa: E402
from controller.harness.cell import start_simulators, with_urls  # noqa: E402
from controller.job.read import job_from_dict  # noqa: E402
from controller.motion.cnc5 import Five  # noqa: E402
from controller.motion.kinematics import Trunnion  # noqa: E402
from core.realtime import elevate  # noqa: E402
from drivers.grbl import CncLink  # noqa: E402


def run_queue_s() -> float:
    """Seconds this process's threads have waited to run (Linux schedstat)."""
    tot = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            tot += int(Path(f"/proc/self/task/{tid}/schedstat").read_text().split()[1])
        except (OSError, IndexError, ValueError):
            pass
    return tot / 1e9


async def programs(part: str, passes: int) -> list[tuple[list[str], list[str]]]:
    """(approach, weld) lines per pass, as the executor streams them."""
    job = job_from_dict(plan5(tilted_tube() if part == "tube" else cone_frustum()))
    five = Five(Trunnion.from_config(kin_cfg("AB").kinematics))
    await five.post_job(job, 2.0, 115200)
    out = []
    for li, la in enumerate(job.layers):
        for pi, p in enumerate(la.passes):
            five.use(li, pi)
            first = (float(p.points[0][0]), float(p.points[0][1]), float(p.points[0][2]))
            out.append((five.approach_lines(first, 5.0, 3000.0), ["M3 S1000"] + five.weld_lines(0, p.speeds()) + ["M5"]))
    return out[:passes]


async def stream(url: str, scale: float, progs: list[tuple[list[str], list[str]]]) -> dict:
    elevate("bench.stream5")   # the controller's loop runs so in a build
    link = CncLink(url, line_scale=scale)
    await link.connect()
    await link.home()
    n, wall, cpu, rq = 0, 0.0, 0.0, 0.0
    for approach, weld in progs:
        await link.stream(approach)
        c0, w0, q0 = time.process_time(), time.monotonic(), run_queue_s()
        await link.stream(weld)
        n, wall, cpu, rq = (n + len(weld), wall + time.monotonic() - w0, cpu + time.process_time() - c0,
                            rq + run_queue_s() - q0)
    await link.close()
    return {"lines": n, "wall_ms_per_line": round(wall / n * 1000, 3), "cpu_ms_per_line": round(cpu / n * 1000, 3),
            "run_queue_ms_per_line": round(rq / n * 1000, 3)}


def stand_still(log: Path) -> dict:
    """From cnc.jsonl: weld blocks that started after the previous one ended (process time)."""
    gaps, prev = [], None
    for row in (log / "cnc.jsonl").read_text().splitlines():
        r = json.loads(row)
        ln = r.get("line", "")
        if ln.startswith("G1") and "F" in ln and not ln.startswith("G1Z"):
            if prev is not None:
                gaps.append(r["t"] - prev - 60.0 / float(ln.rsplit("F", 1)[1]))
            prev = r["t"]
        else:
            prev = None
    g = np.asarray(gaps or [0.0])
    return {"still_s": round(float(g.clip(0).sum()), 3), "max_gap_ms": round(float(g.max()) * 1000, 1),
            "gaps_over_2ms": int((g > 0.002).sum())}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.stream5")
    ap.add_argument("--scale", type=float, default=10.0)
    ap.add_argument("--passes", type=int, default=8)
    ap.add_argument("--part", choices=("tube", "frustum"), default="tube")
    a = ap.parse_args(argv)
    progs = asyncio.run(programs(a.part, a.passes))
    with tempfile.TemporaryDirectory() as d:
        log = Path(d)
        # the CNC's simulator alone, in this process (controller/harness/cell.py)
        cfg, h = asyncio.run(start_simulators(with_urls(kin_cfg("AB"), {}, time_scale=a.scale), level_sim(),
                                              log_dir=log, modules=["sims.cnc.sim"]))
        assert h is not None
        try:
            fig = asyncio.run(stream(cfg.devices.cnc.url, a.scale, progs))
        finally:
            h.stop()
        fig.update(stand_still(log))
    print(json.dumps({"part": a.part, "scale": a.scale, **fig}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

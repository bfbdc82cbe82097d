"""Builds against devices that flood, lie, garble, go mute or stay faulted (issue 13).

    python -m bench.lying_devices [--runs 10] [--modes flood,lie,garble,mute,latched] [--scale 20]

Each run builds a small job (3 layers of 2 beads) on the in-process simulators with the robot
misbehaving from its N-th executed move (N varies with the run), and measures:

- end: the build's state (fault / complete), seconds from the misbehaviour's start
  (the simulator's faults.jsonl) to the latched fault;
- held: weld start dropped on the power source, the robot not moving 0.5 s later;
- journal: SQLite integrity_check;
- account: the controller's deposited length (journal beads, from measurements) minus the
  simulator's deposit log (ground truth), in mm; "complete" with metal missing is a failure.

`latched`: the power source starts with error 50 latched (persisted in its log dir): the run
must move nothing and say how to clear it; a second run with reset_errors completes.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import sqlite3
import statistics
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

MODES = ("flood", "lie", "garble", "mute", "latched")
BUILD_BUDGET_S = 90.0   # a run longer than this is a hang


def small_job(n_layers: int = 3, side: float = 20.0, h: float = 1.0) -> dict:
    layers = []
    for li in range(n_layers):
        z = h * (li + 1)
        outer = [[0, 0, z], [side, 0, z], [side, side, z], [0, side, z], [0, 0.5, z]]
        inner = [[5, 5, z], [15, 5, z], [15, 15, z], [5, 15, z], [5, 5.5, z]]
        layers.append({"index": li, "z_mm": z, "height_mm": h, "passes": [
            {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": 600, "wfs_m_min": 5.5,
             "points": outer},
            {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": 600, "wfs_m_min": 5.5,
             "points": inner}]})
    return {"schema": "cell-job/1", "source": {"file": "lying.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.69, "model": "tangent"},
            "layers": layers, "summary": {}}


def deposit_log_mm(path: Path) -> float:
    if not path.exists():
        return 0.0
    total = 0.0
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            s = json.loads(line)
        except json.JSONDecodeError:
            continue
        total += math.dist(s["from"], s["to"])
    return total


def planned_mm(job: dict) -> float:
    return sum(math.dist(a, b) for la in job["layers"] for p in la["passes"]
               for a, b in zip(p["points"], p["points"][1:]))


def _started(log: Path, mode: str) -> float | None:
    f = log / "faults.jsonl"
    if not f.exists():
        return None
    for line in f.read_text().splitlines():
        r = json.loads(line)
        if r["fault"] == mode:
            return float(r["t_mono"])
    return None


async def _build(tmp: Path, spec: str, scale: float, reset_errors: bool = False) -> dict[str, Any]:
    # lazy: only this benchmark's path needs it
    from controller.harness.cell import open_cell
    from controller.harness.sim import with_urls
    from controller.job.read import job_from_dict
    from core.config import load_cell, load_sim

    cfg = with_urls(load_cell(), {}, time_scale=scale)
    log = tmp / "log"
    out: dict[str, Any] = {}
    async with open_cell(cfg, sim=load_sim(), log_dir=log, faults=spec, runs_dir=tmp / "runs", connect=False) as ctl:
        harness = ctl.simulators
        ctl.options.reset_errors = reset_errors
        await ctl.connect(reply_timeout_ms=500.0)
        job = small_job()
        ctl.open_job(job_from_dict(job))
        t0 = time.monotonic()
        try:
            res = await asyncio.wait_for(ctl.start(), BUILD_BUDGET_S)
            out["state"] = res.state
            out["defects"] = res.defects
        except asyncio.TimeoutError:
            out["state"] = "hang"
        out["wall_s"] = time.monotonic() - t0
        trips = ctl.interlocks.trips if ctl.interlocks else []
        out["t_fault"] = trips[0].t_detect if trips else None
        out["alarm"] = trips[0].message if trips else None
        power = harness.sim("power_source")
        robot = harness.sim("robot")
        t1 = time.monotonic()  # weld start must fall within a power-source cycle or two of the trip
        while power.cmd.bits.get("weld_start") and time.monotonic() - t1 < 0.5:
            await asyncio.sleep(0.005)
        out["weld_start"] = bool(power.cmd.bits.get("weld_start"))
        p0 = tuple(robot.pos)
        await asyncio.sleep(0.5)
        out["moving"] = tuple(robot.pos) != p0
        out["robot_moves"] = robot.executed_count
        ctl.journal.flush()
        out["controller_mm"] = float(ctl.journal.query("SELECT coalesce(sum(length_mm), 0) FROM beads")[0][0])
        out["planned_mm"] = planned_mm(job)
        jpath = ctl.run_dir / "journal.sqlite"
    out["sim_mm"] = deposit_log_mm(log / "deposit.jsonl")
    with sqlite3.connect(str(jpath)) as db:
        out["journal_ok"] = db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    out["log"] = log
    return out


def one_run(mode: str, run: int, tmp: Path, scale: float = 20.0) -> dict[str, Any]:
    """One build with the robot misbehaving (or the source latched); the figures of it."""
    if mode == "latched":
        r = asyncio.run(_build(tmp, "latched_error=50", scale))
        r2 = asyncio.run(_build(tmp, "latched_error=50", scale, reset_errors=True))
        r["second_state"] = r2["state"]
        r["second_sim_mm"] = r2["sim_mm"]
        r["ok"] = (r["state"] == "fault" and r["robot_moves"] == 0 and "reset-errors" in (r["alarm"] or "")
                   and r2["state"] == "complete" and r["journal_ok"])
        return r
    move = 15 + 23 * run  # spread the start over the build
    r = asyncio.run(_build(tmp, f"{mode}@move={move}", scale))
    t_start = _started(r["log"], mode)
    r["latency_s"] = (r["t_fault"] - t_start) if (r["t_fault"] and t_start) else None
    r["account_diff_mm"] = r["controller_mm"] - r["sim_mm"]
    if r["state"] == "complete":
        ok = abs(r["sim_mm"] - r["planned_mm"]) < 1.0 and abs(r["account_diff_mm"]) <= 1.0
    else:
        ok = (r["state"] == "fault" and r["latency_s"] is not None and r["latency_s"] < 5.0
              and not r["weld_start"] and not r["moving"] and abs(r["account_diff_mm"]) <= 1.0)
    r["ok"] = bool(ok and r["journal_ok"])
    return r


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--scale", type=float, default=20.0)
    a = ap.parse_args(argv)
    bad = 0
    for mode in a.modes.split(","):
        rows = []
        for k in range(a.runs):
            with TemporaryDirectory() as d:
                r = one_run(mode, k, Path(d), a.scale)
            r.pop("log", None)
            rows.append(r)
            print(json.dumps({"mode": mode, "run": k, **{key: (round(v, 3) if isinstance(v, float) else v)
                                                            for key, v in r.items()}}), flush=True)
        lat = [r["latency_s"] for r in rows if r.get("latency_s") is not None]
        diffs = [abs(r.get("account_diff_mm", 0.0)) for r in rows]
        n_ok = sum(r["ok"] for r in rows)
        bad += len(rows) - n_ok
        print(json.dumps({"mode": mode, "runs": len(rows), "ok": n_ok,
                          "states": {s: sum(r["state"] == s for r in rows) for s in {r["state"] for r in rows}},
                          "latency_s_max": round(max(lat), 3) if lat else None,
                          "latency_s_median": round(statistics.median(lat), 3) if lat else None,
                          "account_diff_mm_max": round(max(diffs), 3) if diffs else None}), flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())

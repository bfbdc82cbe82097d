"""Kill the controller with SIGKILL at random moments of a build against `cell sim up`, resume
each time, then prove against the simulators' own logs (docs/contract.md §6a) that every planned weld
segment was deposited exactly once (re-arc overlaps of at most 2 mm per restart) and that the
robot executed no sequence number twice. `rearc_overlap_*`: the signed overlap at each re-arc
(deposit already there beyond the point where a later arc started; negative would be a gap);
`max_overlap_mm` is the checker's, which merges the stretches of nearby re-arcs.

    .venv/bin/python -m bench.kill_resume [--kills 20] [--seed 1] [--quick] [--keep DIR]
        [--max-step 0.5] [--speed 600] [--time-scale 1] [--kill-at 0.25,0.6] [--runs 5]

`--kill-at 0.25,0.6 --runs 5` (issue 26): two kills per build, once the deposit log holds a
quarter and 60 % of the plan, five builds; `lost_per_restart_mm` / `twice_per_restart_mm` are
the gap / double deposit at each re-arc, judged from deposit.jsonl.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench._coverage import coverage, exec_log_duplicates, read_segments  # noqa: E402

MAX_STEP_MM = 0.5     # weld moves (default of --max-step)


def soak_job(n_layers: int, speed: float = 600.0) -> dict:
    """Two square perimeters per layer (30 mm and 20 mm), 600 mm/min: ~20 s of arc per layer."""
    layers = []
    for li in range(n_layers):
        z = 1.0 * (li + 1)
        outer = [[0, 0, z], [30, 0, z], [30, 30, z], [0, 30, z], [0, 0.5, z]]
        inner = [[5, 5, z], [25, 5, z], [25, 25, z], [5, 25, z], [5, 5.5, z]]
        layers.append({"index": li, "z_mm": z, "height_mm": 1.0, "passes": [
            {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": speed, "wfs_m_min": 5.5,
             "points": outer},
            {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": speed, "wfs_m_min": 5.5,
             "points": inner}]})
    return {"schema": "cell-job/1", "source": {"file": "soak.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.69, "model": "tangent"},
            "layers": layers, "summary": {}}


def _along(P: list, q: list, tol: float = 0.05) -> float | None:
    """Length along polyline P of point q (first match), None when q is off it."""
    acc = 0.0
    for a, b in zip(P, P[1:]):
        d = [bi - ai for ai, bi in zip(a, b)]
        L2 = sum(v * v for v in d)
        if L2 <= 1e-18:
            continue
        t = max(0.0, min(1.0, sum((qi - ai) * v for qi, ai, v in zip(q, a, d)) / L2))
        if math.dist([ai + t * v for ai, v in zip(a, d)], q) <= tol:
            return acc + t * math.sqrt(L2)
        acc += math.sqrt(L2)
    return None


def rearc_joints(passes: list, segments: list[dict], pause_s: float = 0.3) -> list[float]:
    """Signed overlap at every re-arc (deposit of a later arc starting where an earlier one
    ended): positive = laid twice, negative = a gap. Joints between consecutive moves of one
    arc (no pause in time) are not re-arcs."""
    out = []
    for P in passes:
        iv = []
        for sg in segments:
            a, b = _along(P, sg["from"]), _along(P, sg["to"])
            if a is not None and b is not None and b > a + 1e-6:
                iv.append((sg["t0"], sg["t1"], a, b))
        iv.sort()
        for k in range(1, len(iv)):
            t0, _t1, a, _b = iv[k]
            if t0 - iv[k - 1][1] > pause_s and a > 1e-3:   # a new arc, not at the pass's start
                reach = max((x[3] for x in iv[:k]), default=0.0)
                out.append(reach - a)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cell(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "controller.cli.main", *args], cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, start_new_session=True, **kw)


def _deposited_mm(path: Path) -> float:
    """Length deposited so far according to the simulators' deposit log."""
    return sum(math.dist(sg["from"], sg["to"]) for sg in read_segments(path))


def _setup(a: argparse.Namespace, work: Path) -> tuple[Path, Path, dict]:
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    cfg["cell"]["time_scale"] = a.time_scale  # 1: real time, as the watchdog and link timings are
    cfg["devices"]["robot"]["url"] = f"socket://127.0.0.1:{_free_port()}"
    cfg["devices"]["cnc"]["url"] = f"socket://127.0.0.1:{_free_port()}"
    cfg["devices"]["power_source"]["url"] = f"tcp://127.0.0.1:{_free_port()}"
    cfg["devices"]["cellio"]["url"] = f"tcp://127.0.0.1:{_free_port()}"
    cfgp = work / "cell.yaml"
    cfgp.write_text(yaml.safe_dump(cfg))
    job = soak_job(a.layers, a.speed)
    jobp = work / "soak.job.json"
    jobp.write_text(json.dumps(job))
    return cfgp, jobp, job


def _kill_when_due(p: subprocess.Popen, rng: random.Random, kill_at: list[float] | None, kills: int,
                   planned_mm: float, logs: Path) -> bool:
    """Once `cell run` / `cell resume` is building, wait for the moment to kill it: a random one,
    or (with `kill_at`) until the deposit log holds the next fraction of the plan. SIGKILL it if
    it is still running then; True when it was killed."""
    started = threading.Event()

    def watch(proc: subprocess.Popen = p, ev: threading.Event = started) -> None:
        for line in proc.stderr:
            if "passes done" in line or "building" in line:
                ev.set()
    threading.Thread(target=watch, daemon=True).start()
    started.wait(20)
    if kill_at is None:
        time.sleep(rng.uniform(0.3, 4.0))  # a random moment of the build
    else:  # once the deposit reaches the fraction (the arc is on)
        goal = kill_at[kills] * planned_mm
        while p.poll() is None and _deposited_mm(logs / "deposit.jsonl") < goal:
            time.sleep(0.01)
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        return True
    return False


def _run_until_complete(a: argparse.Namespace, cfgp: Path, jobp: Path, runs: Path, logs: Path,
                        rng: random.Random, kill_at: list[float] | None, n_kills: int,
                        planned_mm: float) -> tuple[int, dict | None]:
    """`cell run`, then `cell resume` after each kill, until the build completes: (kills, the
    last run's JSON summary)."""
    kills = 0
    final: dict | None = None
    attempt = 0
    while True:
        args = ["run", str(jobp)] if attempt == 0 else ["resume"]
        p = _cell(*args, "--cell-config", str(cfgp), "--runs", str(runs), "--json", "--max-step",
                  str(a.max_step), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        attempt += 1
        if kills < n_kills and _kill_when_due(p, rng, kill_at, kills, planned_mm, logs):
            kills += 1
            continue
        out, _err = p.communicate(timeout=600)
        if p.returncode not in (0, 1):
            raise SystemExit(f"controller exited {p.returncode}: {_err[-400:]}")
        final = json.loads(out.strip().splitlines()[-1])
        if final["state"] == "complete":
            break
        if attempt > n_kills + 10:
            raise SystemExit(f"build does not complete: {final}")
    return kills, final


def _kill_figures(a: argparse.Namespace, passes: list, logs: Path, kills: int, final: dict | None,
                  wall: float) -> dict:
    """The build's figures from the simulators' deposit and robot logs."""
    segs = read_segments(logs / "deposit.jsonl")
    cov = coverage(passes, segs)
    dups = exec_log_duplicates(logs / "robot.jsonl")
    joints = rearc_joints(passes, segs)
    restarts = kills
    # per restart: at each re-arc, deposit laid twice (positive overlap) or lost (a gap)
    twice = [max(0.0, j) for j in joints]
    lost = [max(0.0, -j) for j in joints]
    ok = cov.missing_mm < 0.05 and max(cov.overlaps_mm, default=0.0) <= 2.0 and dups == 0 \
        and min(joints, default=0.0) > -0.01
    return {"kills": kills, "state": final["state"] if final else None, "wall_s": round(wall, 1),
            "planned_mm": round(cov.planned_mm, 1), "deposited_mm": round(cov.deposited_mm, 2),
            "missing_mm": round(cov.missing_mm, 3), "excess_mm": round(cov.excess_mm, 3),
            "excess_per_restart_mm": round(cov.excess_mm / max(restarts, 1), 3),
            "overlaps": len(cov.overlaps_mm), "max_overlap_mm": round(max(cov.overlaps_mm, default=0.0), 3),
            "mean_overlap_mm": round(sum(cov.overlaps_mm) / max(len(cov.overlaps_mm), 1), 3),
            "max_step_mm": a.max_step, "speed_mm_min": a.speed, "time_scale": a.time_scale,
            "rearcs": len(joints), "rearc_overlap_max_mm": round(max(joints, default=0.0), 3),
            "rearc_overlap_mean_mm": round(sum(joints) / max(len(joints), 1), 3),
            "rearc_overlap_min_mm": round(min(joints, default=0.0), 3),
            "lost_per_restart_mm": [round(v, 3) for v in lost],
            "twice_per_restart_mm": [round(v, 3) for v in twice],
            "robot_seq_duplicates": dups, "ok": ok, "logs": str(logs)}


def build_with_kills(a: argparse.Namespace, work: Path, rng: random.Random,
                     kill_at: list[float] | None) -> dict:
    """One build against `cell sim up` in its own process: SIGKILL of `cell run` / `cell resume`
    at random moments (`a.kills` of them) or, with `kill_at`, once the deposit log holds each
    given fraction of the planned length; resumed until complete. Figures from the sims' logs."""
    work.mkdir(parents=True, exist_ok=True)
    cfgp, jobp, job = _setup(a, work)
    logs, runs = work / "simlog", work / "runs"
    passes = [p["points"] for la in job["layers"] for p in la["passes"]]
    planned_mm = sum(math.dist(p, q) for P in passes for p, q in zip(P, P[1:]))
    n_kills = len(kill_at) if kill_at is not None else a.kills
    sim = _cell("sim", "up", "--cell-config", str(cfgp), "--log", str(logs), stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL, text=True)
    t_start = time.monotonic()
    kills = 0
    final: dict | None = None
    try:
        for _ in range(4):  # one JSON line per simulator
            if not sim.stdout.readline():
                raise SystemExit("cell sim up did not start")
        time.sleep(0.3)
        kills, final = _run_until_complete(a, cfgp, jobp, runs, logs, rng, kill_at, n_kills, planned_mm)
    finally:
        try:
            os.killpg(sim.pid, signal.SIGINT)
            sim.wait(10)
        except Exception:
            os.killpg(sim.pid, signal.SIGKILL)
    wall = time.monotonic() - t_start
    return _kill_figures(a, passes, logs, kills, final, wall)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.kill_resume")
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--layers", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="5 kills, 2 layers")
    ap.add_argument("--keep", default=None, metavar="DIR", help="work here and keep the logs")
    ap.add_argument("--max-step", type=float, default=MAX_STEP_MM, help="weld move length, mm")
    ap.add_argument("--speed", type=float, default=600.0, help="weld speed, mm/min")
    ap.add_argument("--time-scale", type=float, default=1.0, help="process time / wall time")
    ap.add_argument("--kill-at", default=None, metavar="F,F",
                    help="kill once the deposit holds these fractions of the plan (e.g. 0.25,0.6) "
                         "instead of at random moments")
    ap.add_argument("--runs", type=int, default=1, help="repeat the whole build this many times")
    a = ap.parse_args(argv)
    if a.quick:
        a.kills, a.layers = 5, 2
    rng = random.Random(a.seed)
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="kill_resume-"))
    kill_at = [float(v) for v in a.kill_at.split(",")] if a.kill_at else None
    figs = []
    for r in range(a.runs):
        fig = build_with_kills(a, work / f"run{r}" if a.runs > 1 else work, rng, kill_at)
        figs.append(fig)
        print(json.dumps(fig), flush=True)
    if a.runs > 1:
        lost = [v for f in figs for v in f["lost_per_restart_mm"]]
        twice = [v for f in figs for v in f["twice_per_restart_mm"]]
        print(json.dumps({"runs": a.runs, "restarts": sum(f["kills"] for f in figs),
                          "rearcs": len(twice), "complete": sum(f["state"] == "complete" for f in figs),
                          "lost_per_restart_max_mm": round(max(lost, default=0.0), 3),
                          "lost_per_restart_mean_mm": round(sum(lost) / max(len(lost), 1), 3),
                          "twice_per_restart_max_mm": round(max(twice, default=0.0), 3),
                          "twice_per_restart_mean_mm": round(sum(twice) / max(len(twice), 1), 3),
                          "missing_mm_max": max(f["missing_mm"] for f in figs),
                          "excess_per_restart_mm_max": max(f["excess_per_restart_mm"] for f in figs),
                          "ok": all(f["ok"] for f in figs)}))
    return 0 if all(f["ok"] for f in figs) else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

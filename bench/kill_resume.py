"""Kill the controller with SIGKILL at random moments of a build against `cell sim up`, resume
each time, then prove against the simulators' own logs (DESIGN.md §6a) that every planned weld
segment was deposited exactly once (re-arc overlaps of at most 2 mm per restart) and that the
robot executed no sequence number twice.

    .venv/bin/python -m bench.kill_resume [--kills 20] [--seed 1] [--quick] [--keep DIR]
"""
from __future__ import annotations

import argparse
import json
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

MAX_STEP_MM = 0.5     # weld moves: the re-arc overlap is one move + (watchdog 100 ms + burn-back) of travel


def soak_job(n_layers: int) -> dict:
    """Two square perimeters per layer (30 mm and 20 mm), 600 mm/min: ~20 s of arc per layer."""
    layers = []
    for li in range(n_layers):
        z = 1.0 * (li + 1)
        outer = [[0, 0, z], [30, 0, z], [30, 30, z], [0, 30, z], [0, 0.5, z]]
        inner = [[5, 5, z], [25, 5, z], [25, 25, z], [5, 25, z], [5, 5.5, z]]
        layers.append({"index": li, "z_mm": z, "height_mm": 1.0, "passes": [
            {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": 600, "wfs_m_min": 5.5,
             "points": outer},
            {"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": 600, "wfs_m_min": 5.5,
             "points": inner}]})
    return {"schema": "cell-job/1", "source": {"file": "soak.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.69, "model": "tangent"},
            "layers": layers, "summary": {}}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cell(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "controller.cli.main", *args], cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, start_new_session=True, **kw)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="bench.kill_resume")
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--layers", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="5 kills, 2 layers")
    ap.add_argument("--keep", default=None, metavar="DIR", help="work here and keep the logs")
    a = ap.parse_args(argv)
    if a.quick:
        a.kills, a.layers = 5, 2
    rng = random.Random(a.seed)
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="kill_resume-"))
    work.mkdir(parents=True, exist_ok=True)
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    cfg["cell"]["time_scale"] = 1.0  # real time: the watchdog and link timings are real too
    cfg["devices"]["robot"]["url"] = f"socket://127.0.0.1:{_free_port()}"
    cfg["devices"]["cnc"]["url"] = f"socket://127.0.0.1:{_free_port()}"
    cfg["devices"]["power_source"]["url"] = f"tcp://127.0.0.1:{_free_port()}"
    cfg["devices"]["cellio"]["url"] = f"tcp://127.0.0.1:{_free_port()}"
    cfgp = work / "cell.yaml"
    cfgp.write_text(yaml.safe_dump(cfg))
    job = soak_job(a.layers)
    jobp = work / "soak.job.json"
    jobp.write_text(json.dumps(job))
    logs, runs = work / "simlog", work / "runs"
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
        attempt = 0
        while True:
            args = ["run", str(jobp)] if attempt == 0 else ["resume"]
            p = _cell(*args, "--cell-config", str(cfgp), "--runs", str(runs), "--json", "--max-step",
                      str(MAX_STEP_MM), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            attempt += 1
            if kills < a.kills:
                started = threading.Event()

                def watch(proc: subprocess.Popen = p, ev: threading.Event = started) -> None:
                    for line in proc.stderr:
                        if "passes done" in line or "building" in line:
                            ev.set()
                threading.Thread(target=watch, daemon=True).start()
                started.wait(20)
                time.sleep(rng.uniform(0.3, 4.0))  # a random moment of the build
                if p.poll() is None:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                    kills += 1
                    continue
            out, _err = p.communicate(timeout=600)
            if p.returncode not in (0, 1):
                raise SystemExit(f"controller exited {p.returncode}")
            final = json.loads(out.strip().splitlines()[-1])
            if final["state"] == "complete":
                break
            if attempt > a.kills + 10:
                raise SystemExit(f"build does not complete: {final}")
    finally:
        try:
            os.killpg(sim.pid, signal.SIGINT)
            sim.wait(10)
        except Exception:
            os.killpg(sim.pid, signal.SIGKILL)
    wall = time.monotonic() - t_start
    passes = [p["points"] for la in job["layers"] for p in la["passes"]]
    cov = coverage(passes, read_segments(logs / "deposit.jsonl"))
    dups = exec_log_duplicates(logs / "robot.jsonl")
    restarts = kills
    ok = cov.missing_mm < 0.05 and max(cov.overlaps_mm, default=0.0) <= 2.0 and dups == 0
    fig = {"kills": kills, "state": final["state"] if final else None, "wall_s": round(wall, 1),
           "planned_mm": round(cov.planned_mm, 1), "deposited_mm": round(cov.deposited_mm, 2),
           "missing_mm": round(cov.missing_mm, 3), "excess_mm": round(cov.excess_mm, 3),
           "excess_per_restart_mm": round(cov.excess_mm / max(restarts, 1), 3),
           "overlaps": len(cov.overlaps_mm), "max_overlap_mm": round(max(cov.overlaps_mm, default=0.0), 3),
           "robot_seq_duplicates": dups, "ok": ok, "logs": str(logs)}
    print(json.dumps(fig))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

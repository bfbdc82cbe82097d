"""`cell repair run` against `cell sim up` (issue 36): `python -m bench.repair_sim_up [--shape S]`.

The shipped config/cell.yaml with its platform set to `cnc` (and free local ports, so it can run
beside other sessions), `cell sim up` in a process of its own with the stock posed on the table
as `cell demo --repair` poses it, then `cell repair run JOB --json` as a user types it (finishing
on: stock probe, machining, verify against CAD). Prints one JSON line: the exit code, the run's
state, the time scale the build ran at, the stock, the machining and the verify (every touch
against CAD), or the refusal and whether any motion came before it (the CNC simulator's log).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from bench.repair import worn_parts
from controller.harness.repair_parts import posed_sim
from tests.sim_processes import free_ports, read_devices

ROOT = Path(__file__).resolve().parents[1]


def _cell(tmp: Path) -> Path:
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    p = free_ports(4)
    cfg["cell"]["platform"] = "cnc"
    for name, port, scheme in (("robot", p[0], "socket"), ("cnc", p[1], "socket"),
                               ("power_source", p[2], "tcp"), ("cellio", p[3], "tcp")):
        cfg["devices"][name]["url"] = f"{scheme}://127.0.0.1:{port}"
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    for name in ("materials", "power_source.dbc"):   # what cell.yaml names beside it
        os.symlink(ROOT / "config" / name, tmp / name)
    return path


def one(tmp: Path, shape: str) -> dict[str, Any]:
    cad, stock = worn_parts(tmp, shape)
    job = tmp / "job.json"
    lax = ["--allow-underfill", "--allow-overhang"] if shape == "edge" else []
    subprocess.run([sys.executable, "-m", "controller.cli.main", "repair", "plan", str(cad), "--stock", str(stock),
                    "--width", "4", "--allowance", "0.5", "--out", str(job), *lax], cwd=ROOT, check=True,
                   capture_output=True)
    cell = _cell(tmp)
    (tmp / "sim.yaml").write_text(yaml.safe_dump(posed_sim(stock, 1.2, -0.8, 3.0, (2.0, -1.5, 0.5)).model_dump(mode="json")))
    sim = subprocess.Popen([sys.executable, "-m", "controller.cli.main", "sim", "up", "--cell-config", str(cell),
                            "--config", str(tmp / "sim.yaml"), "--log", str(tmp / "logs")],
                           cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    try:
        read_devices(sim)
        run = subprocess.run([sys.executable, "-m", "controller.cli.main", "repair", "run", str(job), "--cell-config",
                              str(cell), "--json", "--runs", str(tmp / "runs")], cwd=ROOT, capture_output=True, text=True)
    finally:
        sim.terminate()
        sim.wait(30)
    out: dict[str, Any] = {"shape": shape, "exit": run.returncode, "wall_s": round(time.time() - t0, 1),
                           "stderr_first": run.stderr.splitlines()[0][:200] if run.stderr else ""}
    try:
        rep = json.loads(run.stdout)
    except json.JSONDecodeError:
        return {**out, "json": False, "stdout": run.stdout[-300:]}
    if "error" in rep:
        log = tmp / "logs" / "cnc.jsonl"
        moves = log.read_text().splitlines() if log.is_file() else []    # one row per stretch of motion
        return {**out, "state": "refused", "error": str(rep["error"])[:300], "motions_before": len(moves)}
    v, mc, st = rep["verify"], rep.get("machining", {}), rep.get("stock", {})
    return {**out, "state": rep["state"], "time_scale": rep.get("time_scale"), "stock_min_mm": st.get("min_mm"),
            "stock_touches": st.get("points"), "redeposits": len(st.get("redeposits", [])),
            "removal_mean_mm": mc.get("removal_mean_mm"), "verify_max_mm": v["height_error_max_mm"],
            "verify_below_cad_mm": v.get("below_cad_max_mm"), "defects": len(v["defects"])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shape", choices=("pocket", "L", "slot", "edge"), default="pocket")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        print(json.dumps(one(Path(d), a.shape)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

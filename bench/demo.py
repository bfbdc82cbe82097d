"""`make demo` as a figure (issue 35): the demo part built on the robot against the simulators,
several times; per run its end state, defects, layers, the current's range over every bead (the
record's beads.csv: the bead judge's band is ±10 % of the set-point) and the stick-out's range
(the simulator's own deposit.jsonl).

    python -m bench.demo [--runs 3] [--process-control open|layer|path] [--no-feed-forward]

`--no-feed-forward` runs the same demo with one speed per bead (the job planned without the
planner's feed-forward, docs/along-the-path.md), for the before/after figure.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def one_run(runs_dir: Path, extra: list[str]) -> dict[str, Any]:
    t0 = time.monotonic()
    env = {**os.environ, "CELL_RECORD_PLOTS": "0"}
    proc = subprocess.run([sys.executable, "-m", "controller.cli.main", "demo", "--json", "--runs", str(runs_dir), *extra],
                          capture_output=True, text=True, env=env)
    out: dict[str, Any] = {"exit": proc.returncode, "wall_s": round(time.monotonic() - t0, 1)}
    try:
        res = json.loads(proc.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        out["error"] = proc.stderr.strip().splitlines()[-1:] or ["no output"]
        return out
    out.update({"state": res.get("state"), "defects": len(res.get("defects") or []),
                "layers_done": res.get("layers_done"), "passes_done": res.get("passes_done")})
    run_dir = Path(res.get("run_dir") or "")
    beads = run_dir / "beads.csv"
    if beads.exists():
        rows = list(csv.DictReader(beads.open()))
        cur = [(float(r["current_min_a"]), float(r["current_max_a"]), float(r["current_planned_a"])) for r in rows
               if r["current_min_a"] and r["current_planned_a"]]
        out["current_a"] = [round(min(c[0] for c in cur), 1), round(max(c[1] for c in cur), 1)]
        out["current_worst_pct"] = round(100 * max(max(abs(c[0] / c[2] - 1), abs(c[1] / c[2] - 1)) for c in cur), 1)
    dep = run_dir / "sim" / "deposit.jsonl"
    if dep.exists():
        ctwd = [json.loads(ln)["ctwd_mm"] for ln in dep.open() if '"ctwd_mm"' in ln]
        out["ctwd_mm"] = [round(min(ctwd), 2), round(max(ctwd), 2)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--process-control", choices=("open", "layer", "path"), default=None)
    ap.add_argument("--no-feed-forward", action="store_true")
    a = ap.parse_args()
    extra = ["--process-control", a.process_control] if a.process_control else []
    if a.no_feed_forward:
        extra.append("--no-feed-forward")
    results = []
    with tempfile.TemporaryDirectory(prefix="bench-demo-") as tmp:
        for k in range(a.runs):
            results.append(one_run(Path(tmp) / f"run{k}", extra))
            print(json.dumps(results[-1]), flush=True)
    clean = sum(1 for r in results if r.get("state") == "complete" and r.get("defects") == 0 and r.get("exit") == 0)
    print(json.dumps({"runs": len(results), "complete_without_defects": clean,
                      "defects": [r.get("defects") for r in results]}))


if __name__ == "__main__":
    main()

"""Ten cells, one PostgreSQL, an outage (issue 39 targets, docs/records.md).

    .venv/bin/python -m bench.records_fleet [--cells 10] [--jobs 3] [--outage-s 15]

Starts a PostgreSQL server (bench/_postgres.py), then `--cells` simulated cells at once, each a
process of its own (bench/_fleet_cell.py: its simulators, a controller, its own cell.yaml: name,
runs directory, a wire lot, `records.url` = the server) building `--jobs` small jobs one after the
other. Once the first records
are in, the database is stopped for `--outage-s` seconds and started again. After every cell has
finished, `cell records sync` runs once per cell. Then, against every run directory's report.json:
records lost (in a run directory, not in the store), stored twice (rows beyond one per build id,
bead rows beyond the record's), and stored records that differ from their report. Prints one JSON
object. Records are written without plots (CELL_RECORD_PLOTS=0) to spare the shared CPUs.
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

from bench._postgres import running
from controller.records.db import connect
from controller.records.queue import PENDING

ROOT = Path(__file__).resolve().parents[1]


def job(k: int) -> dict[str, Any]:
    """A one-layer job of two short square beads; its side differs per k (a job of its own)."""
    side, z = 12.0 + 2.0 * k, 1.0
    sq = [[0, 0, z], [side, 0, z], [side, side, z], [0, side, z], [0, 0.5, z]]
    inner = [[3, 3, z], [side - 3, 3, z], [side - 3, side - 3, z], [3, side - 3, z], [3, 3.5, z]]
    passes = [{"role": "perimeter", "width_mm": 5, "current_a": 120, "speed_mm_min": 600, "wfs_m_min": 5.5,
               "points": pts} for pts in (sq, inner)]
    return {"schema": "cell-job/1", "source": {"file": f"square{k}.stl", "sha256": "0" * 64, "units": "mm"},
            "material": {"name": "inconel718-1.0mm"},
            "bead": {"width_mm": 5, "height_mm": 1, "step_over_mm": 3.69, "model": "tangent"},
            "layers": [{"index": 0, "z_mm": z, "height_mm": 1.0, "passes": passes}], "summary": {}}


def setup_cell(base: Path, c: int, url: str, jobs: int) -> tuple[Path, Path, list[Path]]:
    """The cell's directory: cell.yaml, its runs directory, its job files."""
    d = base / f"cell-{c:02d}"
    d.mkdir()
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    cfg["cell"].update(name=f"cell-{c:02d}", runs_dir=str(d / "runs"))
    cfg["records"] = {"url": url, "wire_lot": f"LOT-{c % 3}", "operator": f"op-{c}", "connect_timeout_s": 2}
    (d / "cell.yaml").write_text(yaml.safe_dump(cfg))
    files = []
    for k in range(jobs):
        p = d / f"job{k}.json"
        p.write_text(json.dumps(job(k)))
        files.append(p)
    return d / "cell.yaml", d / "runs", files


# Ten cells' device cycles at real-time priority on 2 shared cores starve every other process,
# their record writers included (measured: no record written within 5 min): as root, the cells run
# without CAP_SYS_NICE, time-shared (`--realtime` keeps it), with the in-process simulators' reply
# timeout the test suite uses beside other workers (CELL_SIM_REPLY_TIMEOUT_MS). This bench judges the records,
# not the builds' timing: a build a starved cycle faults still has its record, sent like any other.
_SHARED = ["setpriv", "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", "--"]


def start_cell(cfg: Path, runs: Path, files: list[Path], env: dict[str, str], realtime: bool) -> subprocess.Popen[str]:
    """The cell's process (bench/_fleet_cell.py): its simulators, its controller, its jobs in turn."""
    prefix = _SHARED if os.geteuid() == 0 and not realtime else []
    out = open(cfg.parent / "builds.jsonl", "w", encoding="utf-8")   # noqa: SIM115  (the child's, closed with it)
    return subprocess.Popen([*prefix, sys.executable, "-m", "bench._fleet_cell", str(cfg), str(runs),
                             *map(str, files)], env=env, text=True, stdout=out,
                            stderr=open(cfg.parent / "cell.err", "w", encoding="utf-8"))  # noqa: SIM115


def stored(url: str) -> int:
    try:
        st = connect(url, 1.0)
    except Exception:   # noqa: BLE001  (down: the outage)
        return -1
    try:
        return int(st.rows("SELECT count(*) FROM builds")[0][0])
    finally:
        st.close()


def verify(url: str, runs: list[Path]) -> dict[str, Any]:
    reports = {}
    for r in runs:
        for p in r.glob("*/report.json"):
            rep = json.loads(p.read_text())
            reports[rep["build_id"]] = rep
    st = connect(url)
    try:
        rows = st.rows("SELECT build_id, record FROM builds")
        beads = dict(st.rows("SELECT build_id, count(*) FROM beads GROUP BY build_id"))
    finally:
        st.close()
    ids = [b for b, _ in rows]
    in_db = {b: json.loads(t) for b, t in rows}
    return {"reports": len(reports), "stored": len(rows), "lost": len(set(reports) - set(in_db)),
            "twice": len(ids) - len(set(ids)) + sum(1 for b, n in beads.items() if n != len(in_db[b]["beads"])),
            "differ": sum(1 for b, rep in reports.items() if b in in_db and in_db[b] != rep),
            "states": {st: sum(1 for r in reports.values() if r["state"] == st) for st in
                       sorted({r["state"] for r in reports.values()})},
            "cells_with_records": len({rep["cell"] for rep in reports.values()})}


def sync_and_verify(url: str, cells: list[tuple[Path, Path, list[Path]]], env: dict[str, str]) -> dict[str, Any]:
    """`cell records sync` once per cell, then the store against every run directory's report."""
    out: dict[str, Any] = {}
    runs = [r for _, r, _ in cells]
    out["queued_before_sync"] = sum(1 for r in runs for _ in r.glob(f"*/{PENDING}"))
    out["stored_before_sync"] = stored(url)
    sync = [subprocess.run([sys.executable, "-m", "controller.cli.main", "records", "sync", "--cell-config",
                            str(cfg), "--json"], capture_output=True, text=True, env=env, check=False)
            for cfg, _, _ in cells]
    out["sync_sent"] = sum(json.loads(s.stdout)["sent"] for s in sync if s.stdout.strip())
    out["sync_exit_codes"] = sorted({s.returncode for s in sync})
    out["queued_after_sync"] = sum(1 for r in runs for _ in r.glob(f"*/{PENDING}"))
    out.update(verify(url, runs))
    said = [json.loads(line)["message"] for cfg, _, _ in cells
            for line in (cfg.parent / "builds.jsonl").read_text().splitlines() if line.strip()]
    # what each build's end said: sent, or queued (the outage) and sent later by a next build or the sync
    out["build_ends_queued"] = sum("queued for the record store" in m for m in said)
    out["build_ends_sent"] = sum("sent to the record store" in m for m in said)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench.records_fleet")
    ap.add_argument("--cells", type=int, default=10)
    ap.add_argument("--jobs", type=int, default=3)
    ap.add_argument("--outage-s", type=float, default=15.0)
    ap.add_argument("--realtime", action="store_true", help="let the cells take real-time priority (as root)")
    ap.add_argument("--stagger-s", type=float, default=4.0, help="seconds between the cells' starts")
    ap.add_argument("--outage-after", type=int, default=None, metavar="N",
                    help="stop the database once N records are stored (default: as many as cells)")
    a = ap.parse_args(argv)
    base = Path(tempfile.mkdtemp(prefix="cell-fleet-"))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "CELL_RECORD_PLOTS": "0", "CELL_LOCK_DIR": str(base / "locks"),
           "CELL_SIM_REPLY_TIMEOUT_MS": "2000"}
    out: dict[str, Any] = {"cells": a.cells, "jobs_per_cell": a.jobs, "load_before": os.getloadavg()[0]}
    with running() as srv:
        url = srv.create_db("fleet")
        cells = [setup_cell(base, c, url, a.jobs) for c in range(a.cells)]
        t0 = time.monotonic()
        procs = []
        for cfg, runs, files in cells:   # apart: ten interpreters importing at once crawl
            procs.append(start_cell(cfg, runs, files, env, a.realtime))
            time.sleep(a.stagger_s)
        first = a.outage_after if a.outage_after is not None else a.cells
        while stored(url) < first and time.monotonic() - t0 < 900 and any(p.poll() is None for p in procs):
            time.sleep(0.5)
        out["outage_at_s"], out["stored_before_outage"] = round(time.monotonic() - t0, 1), stored(url)
        srv.stop("fast")
        time.sleep(a.outage_s)
        srv.start()
        out["outage_s"] = a.outage_s
        for p in procs:
            p.wait(timeout=1800)
        out["builds_wall_s"] = round(time.monotonic() - t0, 1)
        out.update(sync_and_verify(url, cells, env))
    out["load_after"] = os.getloadavg()[0]
    out["work_dir"] = str(base)
    print(json.dumps(out, indent=1))
    return 0 if out["lost"] == 0 and out["twice"] == 0 and out["differ"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())

"""Build report: a JSON summary and PNG plots, from the journal alone (docs/contract.md §6).

Plots (matplotlib, Agg): per-layer arc time and heat input, current/voltage traces, part
temperature, and a map of the defects (arc losses, interlock stops) over the planned paths.
"""
from __future__ import annotations

import importlib.metadata
import json
import os
import uuid
from pathlib import Path
from typing import Any

from controller.journal.store import Journal
from controller.report.height import add_height
from controller.report.path_height import add_path
from controller.report.plots import plot_report
from controller.report.record import (
    arc_time_figures,
    travel_speed_summary,
    bead_records,
    iso,
    layer_records,
    write_csv,
)
from core.config import load_material
from core.material import ProcessTolerance
from core.errors import CellError
from planner.job import Job

ALARM_KINDS = ("alarm",)


def summarize(journal: Journal, job: Job | None = None, state: str | None = None,
              operator: str | None = None) -> dict[str, Any]:
    """The build's summary as a JSON-ready dict (times in process seconds, wall clock in ISO UTC)."""
    meta = journal.job() or {}
    scale = journal.latest_time_scale()
    layers_total = len(job.layers) if job else None
    passes_total = sum(len(la.passes) for la in job.layers) if job else None
    done = journal.done_passes()
    layers_done = _layers_done(job, done)
    alarms = journal.alarm_rows()
    defects = _defects(journal, alarms)
    beads = bead_records(journal, job, scale, defects, _tolerance(job))
    per_layer = _per_layer(beads)
    started, ended = journal.wall_clock_span()
    return {
        "job": {"name": meta.get("name"), "hash": meta.get("hash"), "platform": meta.get("platform")},
        "state": state or journal.last_build_state(),
        "started": iso(started), "ended": iso(ended),
        **_provenance(journal, job, operator),
        "layers_total": layers_total,
        "passes_total": passes_total,
        "layers_done": layers_done,
        "passes_done": len(done),
        "arc_starts": journal.arc_start_count(),
        "runs": journal.run_count(),
        "time_scale": scale,
        "arc_time_s": round(sum(d["arc_time_s"] for d in per_layer.values()), 3),
        "arc_time_figures": arc_time_figures(journal, job, scale, beads),
        "travel_speed": travel_speed_summary(beads, job),
        "links": journal.link_rows(),
        "deposit_length_mm": round(sum(d["length_mm"] for d in per_layer.values()), 2),
        "outside_envelope": _outside(job),
        "per_layer": [
            {"layer": k, "arc_time_s": round(v["arc_time_s"], 3), "length_mm": round(v["length_mm"], 2),
             "heat_input_j_mm": round(v["heat_j"] / v["length_mm"], 2) if v["length_mm"] else None}
            for k, v in sorted(per_layer.items())
        ],
        "layers": layer_records(journal, job, scale),
        "beads": beads,
        "alarms": alarms,
        "defects": defects,
        "bead_defects": sum(1 for d in defects if d["state"] == "defect"),
        "tolerance": _tolerance_dict(job),
    }


def _layers_done(job: Job | None, done: set[tuple[int, int]]) -> int:
    """Layers from the first whose every pass is done (the count stops at the first one that is not)."""
    n = 0
    for li, la in enumerate(job.layers if job else ()):
        if not all((li, pi) in done for pi in range(len(la.passes))):
            break
        n += 1
    return n


def _defects(journal: Journal, alarms: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Alarms with a position, then the beads the measurements say were not deposited as planned
    (controller/runtime/bead_check.py)."""
    defects = [a for a in alarms if a["position"] is not None]
    defects += [{"t": d["t"], "message": f"defect: {d['reason']}", "state": "defect", "layer": d["layer"],
                 "pass": d["pass"], "position": d["position"], "run": d["run"], "measured_mm": d["measured_mm"]}
                for d in journal.defect_rows()]
    return defects


def _per_layer(beads: list[dict[str, Any]]) -> dict[int, dict[str, float]]:
    """Arc time, deposited length and heat per layer, over the beads that were built."""
    per_layer: dict[int, dict[str, float]] = {}
    for b in beads:
        if b["status"] == "not built":
            continue
        d = per_layer.setdefault(b["layer"], {"arc_time_s": 0.0, "heat_j": 0.0, "length_mm": 0.0})
        d["arc_time_s"] += b["arc_time_s"] or 0.0
        d["length_mm"] += b["length_measured_mm"] or 0.0
        d["heat_j"] += (b["heat_input_j_mm"] or 0.0) * (b["length_measured_mm"] or 0.0)
    return per_layer


def _material_name(job: Job | None) -> Any:
    return job.material.get("name") if job else None


def _tolerance(job: Job | None) -> ProcessTolerance | None:
    """The process tolerance of the job's material (None when the cell no longer knows it)."""
    name = _material_name(job)
    if not name:
        return None
    try:
        return load_material(str(name)).tolerance
    except CellError:
        return None


def _tolerance_dict(job: Job | None) -> dict[str, Any] | None:
    tol = _tolerance(job)
    if tol is None:
        return None
    return {"current_pct": tol.current_pct, "wfs_pct": tol.wfs_pct, "speed_pct": tol.speed_pct,
            "voltage_min_v": tol.voltage_min_v, "voltage_max_v": tol.voltage_max_v}


def build_id(meta: dict[str, Any]) -> str | None:
    """The build's id, unique across cells and stable over its runs: a UUID of the job's hash and the
    moment its journal was created (the shop's record store keys on it: docs/records.md)."""
    if not meta.get("hash") or meta.get("created") is None:
        return None
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"cell-build:{meta['hash']}:{float(meta['created'])!r}"))


def _provenance(journal: Journal, job: Job | None, operator: str | None) -> dict[str, Any]:
    """Material, wire and its lot, gas, operator, cell and software version of the build.

    Wire lot, gas and operator are the latest run's trace (controller/journal/trace.py); every
    run's is in `traceability`. The gas falls back to the material's, the operator to `--operator`
    of `cell report` first and $CELL_OPERATOR last."""
    name = _material_name(job)
    wire: dict[str, Any] = {"alloy": None, "diameter_mm": None}
    gas = None
    if name:
        try:
            m = load_material(str(name))
            wire = {"alloy": m.name, "diameter_mm": m.wire_diameter_mm}
            gas = m.gas
        except CellError:
            pass  # a material the cell no longer knows: the record keeps its name only
    runs = journal.trace_rows()
    last = runs[-1] if runs else {}
    lot = last.get("wire_lot")
    wire["lot"] = lot
    try:
        version = importlib.metadata.version("cell-controller")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    return {"build_id": build_id(journal.job() or {}), "cell": last.get("cell"), "material": name, "wire": wire,
            "wire_lot": lot, "gas": last.get("gas") or gas, "software_version": version,
            "operator": operator or last.get("operator") or os.environ.get("CELL_OPERATOR"),
            "traceability": runs}


def _outside(job: Job | None) -> list[dict[str, int]]:
    """Passes the planner marked as planned outside the process envelope (`--allow-outside`)."""
    return [{"layer": li, "pass": pi} for li, la in enumerate(job.layers if job else ())
            for pi, pa in enumerate(la.passes) if not pa.inside_envelope]


def write_report(journal: Journal, out_dir: str | Path, job: Job | None = None, plots: bool = True,
                 state: str | None = None, operator: str | None = None, csv_path: str | Path | None = None) -> Path:
    """Write report.json, beads.csv (and the PNGs) into `out_dir`; returns the path of report.json."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(journal, job, state, operator)
    pngs = plot_report(journal, out, job, summary) if plots else []
    summary["plots"] = [p.name for p in pngs]
    add_height(summary, journal, out, plots)   # layer heights: layers[], layers.csv, height.png
    add_path(summary, journal, out, plots)     # heights along the path: path, path.csv, path.png
    summary["csv"] = str(write_csv(summary["beads"], csv_path or out / "beads.csv"))
    path = out / "report.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path

"""The build record's heights along the path (docs/closed-loop.md "Along the path"): per layer
the top measured at every bin (robot) or probe point (CNC) against the layer's planned top, from
the journal's `path` events (controller/runtime/path_control.py).

`path.csv`: one row per layer and position (layer, x, y, along_mm, measured_top_mm, planned_top_mm,
error_mm, speed_factor). `along_mm` is the position along the path of the first layer the loop
measured (each point taken to the nearest point of that path), so layers with alternating or
re-planned passes line up. `path.png`: a heat map of the error, layer × position along the path,
and the profiles of the worst layers (largest RMS). report.json's `path` holds the per-layer
figures (RMS, spread, mean top) and the worst layers.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from controller.journal.store import Journal
from controller.report.figures import new_figure, save

COLUMNS = ("layer", "x_mm", "y_mm", "along_mm", "measured_top_mm", "planned_top_mm", "error_mm", "speed_factor")


def path_records(journal: Journal) -> list[dict[str, Any]]:
    """The latest `path` record of every layer, in layer order."""
    by: dict[int, dict[str, Any]] = {}
    for (msg,) in journal.query("SELECT message FROM events WHERE kind = 'path' ORDER BY id"):
        try:
            d = json.loads(msg)
        except ValueError:
            continue
        by[int(d["layer"])] = d
    return [by[k] for k in sorted(by)]


def path_rows(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per layer and measured position."""
    if not records:
        return []
    ref = np.asarray([r[:2] for r in records[0]["d"]], dtype=float).reshape(-1, 2)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref, axis=0).T))]) if len(ref) > 1 else np.zeros(len(ref))
    out = []
    for rec in records:
        planned, mean = float(rec["planned_top_mm"]), float(rec["mean_top_mm"])
        facs = {(round(x, 3), round(y, 3)): f for x, y, f in rec.get("m", [])}
        for x, y, dv in rec["d"]:
            k = int(np.argmin(np.hypot(ref[:, 0] - x, ref[:, 1] - y))) if len(ref) else 0
            top = mean + float(dv)
            out.append({"layer": int(rec["layer"]), "x_mm": x, "y_mm": y, "along_mm": round(float(cum[k]), 3) if len(cum) else 0.0,
                        "measured_top_mm": round(top, 4), "planned_top_mm": round(planned, 4),
                        "error_mm": round(top - planned, 4), "speed_factor": facs.get((round(x, 3), round(y, 3)))})
    return out


def summary_of(records: list[dict[str, Any]], worst: int = 3) -> dict[str, Any]:
    layers = [{"layer": int(r["layer"]), "rms_mm": r.get("rms_mm"), "spread_mm": r.get("spread_mm"),
               "mean_top_mm": r.get("mean_top_mm"), "planned_top_mm": r.get("planned_top_mm"),
               "source": r.get("source")} for r in records]
    ranked = sorted(layers, key=lambda r: -(r["rms_mm"] or 0.0))
    return {"layers": layers, "worst_layers": [r["layer"] for r in ranked[:worst]],
            "rms_max_mm": ranked[0]["rms_mm"] if ranked else None}


def write_path_csv(rows: list[dict[str, Any]], path: Path) -> Path:
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS))
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r[k]) for k in COLUMNS})
    return path


def plot_path(rows: list[dict[str, Any]], worst: list[int], path: Path) -> Path:
    """path.png: the error heat map (layer × position along the path) and the worst layers' profiles."""
    layers = sorted({int(r["layer"]) for r in rows})
    along = np.asarray([float(r["along_mm"]) for r in rows])
    edges = np.unique(np.round(along, 1))
    if len(edges) < 2:
        edges = np.array([edges[0] - 0.5, edges[0] + 0.5]) if len(edges) else np.array([0.0, 1.0])
    grid = np.full((len(layers), len(edges)), np.nan)
    li = {la: i for i, la in enumerate(layers)}
    for r in rows:
        j = int(np.argmin(np.abs(edges - float(r["along_mm"]))))
        grid[li[int(r["layer"])], j] = float(r["error_mm"])
    fig, ax = new_figure(2, 1, (9, 8))
    lim = max(float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 0.5, 0.1)
    im = ax[0].pcolormesh(np.r_[edges, edges[-1] + (edges[-1] - edges[-2])], np.r_[np.asarray(layers) + 1, layers[-1] + 2] - 0.5,
                          grid, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="flat")
    fig.colorbar(im, ax=ax[0], label="measured − planned top [mm]")
    ax[0].set_xlabel("position along the path [mm]")
    ax[0].set_ylabel("layer")
    for la in worst:
        pr = sorted((float(r["along_mm"]), float(r["error_mm"])) for r in rows if int(r["layer"]) == la)
        if pr:
            ax[1].plot([p[0] for p in pr], [p[1] for p in pr], "o-", ms=3, label=f"layer {la + 1}")
    for v in (-0.5, 0.5):
        ax[1].axhline(v, color="red", ls=":", lw=0.8)
    ax[1].axhline(0.0, color="0.5", lw=0.8)
    ax[1].set_xlabel("position along the path [mm]")
    ax[1].set_ylabel("measured − planned top [mm]")
    ax[1].legend(loc="lower left")
    fig.suptitle("Height along the path: layer × position, and the worst layers")
    return save(fig, path)


def add_path(summary: dict[str, Any], journal: Journal, out: Path, plots: bool) -> None:
    """report.json's `path`, path.csv (and path.png) when the build ran the path loop."""
    records = path_records(journal)
    if not records:
        return
    rows = path_rows(records)
    s = summary_of(records)
    summary["path"] = {**s, "csv": str(write_path_csv(rows, out / "path.csv"))}
    if plots and rows and all(math.isfinite(float(r["error_mm"])) for r in rows):
        summary.setdefault("plots", []).append(plot_path(rows, s["worst_layers"], out / "path.png").name)

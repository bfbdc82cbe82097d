"""The build record's layer heights (docs/closed-loop.md): per layer the planned and measured top,
the stick-out (estimated through the arc or from the probe; in simulation also the truth of
`deposit.jsonl`), the z correction and the trim applied, and what the control did.

From the journal's `layer` / `stick_out` events (controller/runtime/layer_control.py); the truth
from the simulators' `deposit.jsonl` when the run has its sim log (`<run dir>/sim/`, the default
of `cell run --sim`, or the directory given). Written into report.json's `layers[]`, `layers.csv`
and `height.png`.
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

from controller.journal.store import Journal
from controller.report.figures import new_figure, save

COLUMNS = ("layer", "planned_top_mm", "z_mm", "measured_top_mm", "height_error_mm", "source", "stick_out_mm",
           "stick_out_min_mm", "stick_out_max_mm", "true_stick_out_mm", "true_stick_out_min_mm",
           "true_stick_out_max_mm", "z_offset_mm", "correction_mm", "speed_factor", "gain", "action", "added", "mode")


def _events(journal: Journal, kind: str) -> list[dict[str, Any]]:
    out = []
    for (msg,) in journal.query("SELECT message FROM events WHERE kind = ? ORDER BY id", (kind,)):
        try:
            out.append(json.loads(msg))
        except ValueError:
            continue
    return out


def truth_by_z(deposit: Path, zs: dict[float, int]) -> dict[int, list[float]]:
    """The CTWD truth (`ctwd_mm`) of every deposited segment, by the layer whose commanded z it was laid at."""
    out: dict[int, list[float]] = {}
    if not deposit.exists() or not zs:
        return out
    keys = sorted(zs)
    with deposit.open(encoding="utf-8") as fh:
        for line in fh:
            try:
                d = json.loads(line)
            except ValueError:
                continue
            c = d.get("ctwd_mm")
            if c is None:
                continue
            z = float(d["to"][2])
            near = min(keys, key=lambda k: abs(k - z))
            if abs(near - z) < 1e-3:
                out.setdefault(zs[near], []).append(float(c))
    return out


def height_rows(journal: Journal, sim_log: Path | None = None) -> list[dict[str, Any]]:
    """One row per layer the control closed (the latest record of each)."""
    rows: dict[int, dict[str, Any]] = {}
    for d in _events(journal, "layer"):
        rows[int(d["layer"])] = {k: d.get(k) for k in COLUMNS if k in d}
    if sim_log is not None and rows:
        zs = {round(float(r["z_mm"]), 4): la for la, r in rows.items() if r.get("z_mm") is not None}
        for la, vals in truth_by_z(sim_log / "deposit.jsonl", zs).items():
            n = len(vals)
            mid = sorted(vals)[n // 10: n - n // 10] or vals   # the bead's steady part, not its ends
            rows[la].update(true_stick_out_mm=round(sum(vals) / n, 4), true_stick_out_min_mm=round(min(mid), 4),
                            true_stick_out_max_mm=round(max(mid), 4))
    return [rows[k] for k in sorted(rows)]


def merge_layers(layers: list[dict[str, Any]], rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """report.json's `layers[]` with the height columns added (layers only the control saw appended)."""
    by = {int(r["layer"]): r for r in rows}
    out = []
    for la in layers:
        extra = by.pop(int(la["layer"]), {})
        out.append({**la, **{k: v for k, v in extra.items() if k != "layer"}})
    out += [by[k] for k in sorted(by)]
    return out


def write_layers_csv(rows: list[dict[str, Any]], path: Path) -> Path:
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in COLUMNS})
    return path


def _num(rows: list[dict[str, Any]], key: str) -> list[float]:
    return [float(r[key]) if r.get(key) is not None else math.nan for r in rows]


def plot_height(rows: list[dict[str, Any]], path: Path, window: tuple[float, float] | None = None) -> Path:
    """height.png: planned and measured top per layer, the stick-out (estimate, truth) and the correction."""
    x = [int(r["layer"]) + 1 for r in rows]
    fig, ax = new_figure(3, 1, (9, 8), sharex=True)
    ax[0].plot(x, _num(rows, "planned_top_mm"), "k--", lw=1, label="planned top")
    ax[0].plot(x, _num(rows, "measured_top_mm"), "o-", ms=3, color="tab:blue", label="measured top")
    planned = [float(r["planned_top_mm"]) for r in rows if r.get("planned_top_mm") is not None and not r.get("added")]
    if planned:
        ax[0].axhline(max(planned), color="0.5", lw=0.8, label=f"planned final top {max(planned):.2f} mm")
    ax[0].set_ylabel("top [mm]")
    ax[0].legend(loc="upper left")
    ax[1].plot(x, _num(rows, "stick_out_mm"), "o-", ms=3, color="tab:orange", label="stick-out (estimate / probe)")
    if any(r.get("true_stick_out_mm") is not None for r in rows):
        ax[1].plot(x, _num(rows, "true_stick_out_mm"), "-", color="tab:green", label="stick-out (simulation truth)")
        ax[1].fill_between(x, _num(rows, "true_stick_out_min_mm"), _num(rows, "true_stick_out_max_mm"),
                           color="tab:green", alpha=0.2, lw=0)
    if window is not None:
        for v in window:
            ax[1].axhline(v, color="red", ls=":", lw=0.8)
    ax[1].set_ylabel("CTWD [mm]")
    ax[1].legend(loc="upper left")
    ax[2].plot(x, _num(rows, "correction_mm"), "o-", ms=3, color="tab:purple", label="z correction vs plan [mm]")
    ax[2].plot(x, [v - 1.0 for v in _num(rows, "speed_factor")], "s-", ms=3, color="tab:brown",
               label="travel speed trim (factor − 1)")
    ax[2].set_ylabel("correction")
    ax[2].set_xlabel("layer")
    ax[2].legend(loc="lower left")
    fig.suptitle("Layer height: plan, measurement, stick-out and correction")
    return save(fig, path)


def add_height(summary: dict[str, Any], journal: Journal, out: Path, plots: bool, sim_log: Path | None = None) -> None:
    """Merge the layer heights into the summary; write layers.csv (and height.png) next to report.json."""
    log = sim_log if sim_log is not None else out / "sim"
    rows = height_rows(journal, log if (log / "deposit.jsonl").exists() else None)
    if not rows:
        return
    summary["layers"] = merge_layers(summary.get("layers") or [], rows)
    summary["layers_csv"] = str(write_layers_csv(rows, out / "layers.csv"))
    if plots:
        summary.setdefault("plots", []).append(plot_height(rows, out / "height.png").name)

"""The build record's per-bead and per-layer rows, arc-time cross-checks and CSV (DESIGN.md §7).

Everything here is read from the journal (what the devices measured) and the job (what was
planned); times in the journal are wall-clock seconds, scaled by the run's time scale to process
seconds for arc time, travel speed and waits.
"""
from __future__ import annotations

import csv
import datetime as _dt
from pathlib import Path
from typing import Any

from controller.journal import Journal

CSV_COLUMNS = (
    "layer", "pass", "run", "role", "interrupted", "arc_time_s", "length_mm",
    "planned_current_a", "current_mean_a", "current_min_a", "current_max_a",
    "planned_voltage_v", "voltage_mean_v", "voltage_min_v", "voltage_max_v",
    "planned_wfs_m_min", "wfs_mean_m_min", "wfs_min_m_min", "wfs_max_m_min",
    "planned_speed_mm_min", "actual_speed_mm_min", "heat_input_j_mm", "defects",
)
ARC_TIME_TOLERANCE = 0.02  # the three arc-time figures must agree within 2 %


def iso(t: float | None) -> str | None:
    """A Unix time as an ISO 8601 UTC string."""
    if t is None:
        return None
    return _dt.datetime.fromtimestamp(t, tz=_dt.UTC).isoformat(timespec="seconds")


def _planned(job: dict | None, layer: int, pass_: int) -> dict[str, Any]:
    try:
        return dict(job["layers"][layer]["passes"][pass_]) if job else {}
    except (IndexError, KeyError, TypeError):
        return {}


def _wfs_stats(samples: list[tuple], on: float, off: float, layer: int, pass_: int) -> tuple:
    vals = [s[3] for s in samples if on <= s[0] <= off and s[5] == layer and s[6] == pass_ and s[3] is not None]
    if not vals:
        return None, None, None
    return round(sum(vals) / len(vals), 3), round(min(vals), 3), round(max(vals), 3)


def _r(x: float | None, nd: int = 2) -> float | None:
    return None if x is None else round(float(x), nd)


def bead_records(journal: Journal, job: dict | None, scale: float, defects: list[dict]) -> list[dict[str, Any]]:
    """One record per journaled bead: planned against measured."""
    samples = journal.sample_rows()
    out = []
    for b in journal.bead_rows():
        la, pa = b["layer"], b["pass"]
        plan = _planned(job, la, pa)
        arc_s = max(0.0, b["arc_off"] - b["arc_on"]) * scale
        w_mean, w_min, w_max = _wfs_stats(samples, b["arc_on"], b["arc_off"], la, pa)
        out.append({
            "layer": la, "pass": pa, "run": b["run"], "role": plan.get("role"),
            "interrupted": bool(b["interrupted"]), "arc_time_s": round(arc_s, 3),
            "length_mm": round(b["length_mm"], 2),
            "planned_current_a": plan.get("current_a"), "current_mean_a": _r(b["i_mean"]),
            "current_min_a": _r(b["i_min"]), "current_max_a": _r(b["i_max"]),
            "planned_voltage_v": plan.get("voltage_v"), "voltage_mean_v": _r(b["u_mean"]),
            "voltage_min_v": _r(b["u_min"]), "voltage_max_v": _r(b["u_max"]),
            "planned_wfs_m_min": plan.get("wfs_m_min"), "wfs_mean_m_min": w_mean if w_mean is not None
            else _r(b["wfs_mean"], 3), "wfs_min_m_min": w_min, "wfs_max_m_min": w_max,
            "planned_speed_mm_min": plan.get("speed_mm_min", b["speed_mm_min"]),
            "actual_speed_mm_min": round(b["length_mm"] / arc_s * 60.0, 1) if arc_s > 0 else None,
            "heat_input_j_mm": _r(b["heat_input_j_mm"]),
            "defects": sum(1 for d in defects if d.get("layer") == la and d.get("pass") == pa),
        })
    return out


def layer_records(journal: Journal, job: dict | None, scale: float) -> list[dict[str, Any]]:
    """Per layer: interpass temperature at its first arc strike, and the wait since the last layer."""
    beads = journal.bead_rows()
    samples = journal.sample_rows()
    first: dict[int, float] = {}
    last: dict[int, float] = {}
    for b in beads:
        first[b["layer"]] = min(first.get(b["layer"], b["arc_on"]), b["arc_on"])
        last[b["layer"]] = max(last.get(b["layer"], b["arc_off"]), b["arc_off"])
    out = []
    prev_end: float | None = None
    for la in sorted(first):
        t0 = first[la]
        before = [s[4] for s in samples if s[0] <= t0 and s[4] is not None]
        limit = None
        if job and la < len(job["layers"]):
            limit = (job["layers"][la].get("interpass") or {}).get("max_temperature_c")
        out.append({"layer": la, "start": iso(t0), "interpass_temperature_c": _r(before[-1], 1) if before else None,
                    "interpass_limit_c": limit,
                    "wait_s": round((t0 - prev_end) * scale, 1) if prev_end is not None else None})
        prev_end = last[la]
    return out


def arc_time_figures(journal: Journal, job: dict | None, scale: float, beads: list[dict]) -> dict[str, Any]:
    """Three arc times (planned, bead rows, pass-state spans) and whether they agree within 2 %."""
    # planned: the length each bead actually deposited, at its planned travel speed
    planned = sum(b["length_mm"] / b["planned_speed_mm_min"] * 60.0 for b in beads if b["planned_speed_mm_min"])
    measured = sum(b["arc_time_s"] for b in beads)
    spans = sum(max(0.0, off - on) for _l, _p, on, off in journal.arc_on_spans()) * scale
    figs = {"planned_s": round(planned, 1), "beads_s": round(measured, 1), "pass_states_s": round(spans, 1)}
    vals = [v for v in figs.values() if v > 0]
    spread = (max(vals) - min(vals)) / max(vals) if vals else 0.0
    figs["spread"] = round(spread, 4)
    figs["agree"] = spread <= ARC_TIME_TOLERANCE
    if not figs["agree"]:
        figs["note"] = ("arc times disagree by more than 2 %: measured travel speed differs from plan "
                        "(see actual_speed_mm_min per bead)")
    return figs


def write_csv(beads: list[dict[str, Any]], path: str | Path) -> Path:
    """One CSV row per bead (columns CSV_COLUMNS)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with p.open("w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for b in beads:
            w.writerow(b)
    return p

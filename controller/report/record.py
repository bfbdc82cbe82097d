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

from controller.journal.store import Journal

CSV_COLUMNS = (
    "layer", "pass", "run", "role", "interrupted", "arc_time_s", "length_mm",
    "planned_current_a", "current_mean_a", "current_min_a", "current_max_a",
    "planned_voltage_v", "voltage_mean_v", "voltage_min_v", "voltage_max_v",
    "planned_wfs_m_min", "wfs_mean_m_min", "wfs_min_m_min", "wfs_max_m_min",
    "planned_speed_mm_min", "actual_speed_mm_min", "motion_time_s", "starved", "heat_input_j_mm", "defects",
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
    """One record per journaled bead: planned against measured.

    `arc_time_s` is the source's arc-on span (arc stable seen, to arc stable gone), known to one
    bus cycle; `motion_time_s` and `actual_speed_mm_min` come from the robot's EXE reports while
    the arc was stable (controller/runtime/bead_measure.py)."""
    samples = journal.sample_rows()
    out = []
    for b in journal.bead_rows():
        la, pa = b["layer"], b["pass"]
        plan = _planned(job, la, pa)
        arc_s = max(0.0, b["arc_off"] - b["arc_on"]) * scale
        if b.get("wfs_min") is not None:   # every bus cycle of the bead (the samples are thinned)
            w_mean, w_min, w_max = _r(b["wfs_mean"], 3), _r(b["wfs_min"], 3), _r(b["wfs_max"], 3)
        else:
            w_mean, w_min, w_max = _wfs_stats(samples, b["arc_on"], b["arc_off"], la, pa)
            w_mean = w_mean if w_mean is not None else _r(b["wfs_mean"], 3)
        out.append({
            "layer": la, "pass": pa, "run": b["run"], "role": plan.get("role"),
            "interrupted": bool(b["interrupted"]), "arc_time_s": round(arc_s, 3),
            "length_mm": round(b["length_mm"], 2),
            "planned_current_a": plan.get("current_a"), "current_mean_a": _r(b["i_mean"]),
            "current_min_a": _r(b["i_min"]), "current_max_a": _r(b["i_max"]),
            "planned_voltage_v": plan.get("voltage_v"), "voltage_mean_v": _r(b["u_mean"]),
            "voltage_min_v": _r(b["u_min"]), "voltage_max_v": _r(b["u_max"]),
            "planned_wfs_m_min": plan.get("wfs_m_min"), "wfs_mean_m_min": w_mean,
            "wfs_min_m_min": w_min, "wfs_max_m_min": w_max,
            # the speed the bead was commanded at: the plan's, or the layer control's trim of it
            "planned_speed_mm_min": b["speed_mm_min"] or plan.get("speed_mm_min"),
            "actual_speed_mm_min": _r(b.get("speed_actual_mm_min"), 1),
            "motion_time_s": _r(b.get("motion_s"), 3),
            "starved": b.get("starved"),
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


def _polyline_mm(points: list) -> float:
    return sum(sum((b - a) ** 2 for a, b in zip(p, q)) ** 0.5 for p, q in zip(points, points[1:]))


def planned_arc_s(job: dict | None, beads: list[dict[str, Any]]) -> float:
    """The plan's arc time of the passes these beads belong to (whole passes, planned speed)."""
    if not job:
        return 0.0
    seen = set()
    total = 0.0
    for b in beads:
        key = (b["layer"], b["pass"])
        if key in seen:
            continue
        seen.add(key)
        p = _planned(job, *key)
        if p.get("points") and p.get("speed_mm_min"):
            total += _polyline_mm(p["points"]) / float(p["speed_mm_min"]) * 60.0
    return total


def arc_time_figures(journal: Journal, job: dict | None, scale: float, beads: list[dict]) -> dict[str, Any]:
    """Three arc times that must agree within 2 %, and the source's arc-on time beside them.

    plan_s: the job's passes that were built, at their planned length and speed (the figure
    `cell plan` and the demo print); planned_s: the length each bead actually deposited (robot
    EXEs with the arc stable), at its planned speed; measured_s: that length at the speed the
    robot actually kept. arc_on_s (the source's arc-stable span) also holds ignition and crater
    and is known to one 10 ms bus cycle, that is time_scale x 10 ms of process time per edge:
    reported, and its excess over measured_s given per bead, but not part of the agreement.
    """
    plan = planned_arc_s(job, beads)
    planned = sum(b["length_mm"] / b["planned_speed_mm_min"] * 60.0 for b in beads if b["planned_speed_mm_min"])
    measured = sum(b["motion_time_s"] for b in beads if b.get("motion_time_s") is not None)
    arc_on = sum(b["arc_time_s"] for b in beads)
    figs: dict[str, Any] = {"plan_s": round(plan, 1), "planned_s": round(planned, 1),
                            "measured_s": round(measured, 1), "arc_on_s": round(arc_on, 1)}
    vals = [v for v in (plan, planned, measured) if v > 0]
    spread = (max(vals) - min(vals)) / max(vals) if vals else 0.0
    figs["spread"] = round(spread, 4)
    figs["agree"] = spread <= ARC_TIME_TOLERANCE and len(vals) == 3
    n = sum(1 for b in beads if b.get("motion_time_s") is not None)
    figs["arc_on_excess_per_bead_s"] = round((arc_on - measured) / n, 3) if n else None
    figs["bus_cycle_process_s"] = round(0.010 * scale, 3)
    if not figs["agree"]:
        figs["note"] = ("arc times disagree by more than 2 %: beads short of their plan, or travel speed "
                        "differs from plan (see length_mm and actual_speed_mm_min per bead)")
    return figs


def travel_speed_summary(beads: list[dict[str, Any]], job: dict | None = None) -> dict[str, Any]:
    """How far the robot's measured travel speed strayed from the plan, the beads outside the
    material's `tolerance.speed_pct` (flagged, not defects), and the starved beads."""
    try:
        pct = float(((job or {}).get("material") or {}).get("tolerance", {}).get("speed_pct", 10.0))
    except (AttributeError, TypeError, ValueError):
        pct = 10.0
    devs = [(b["actual_speed_mm_min"] / b["planned_speed_mm_min"] - 1.0, b) for b in beads
            if b.get("actual_speed_mm_min") and b.get("planned_speed_mm_min")]
    worst = max((d for d, _ in devs), key=abs) if devs else None
    return {"beads_measured": len(devs), "worst_deviation": _r(worst, 4),
            "within_2pct": bool(devs) and all(abs(d) <= 0.02 for d, _ in devs),
            "tolerance_pct": pct,
            "off_speed_beads": [[b["layer"], b["pass"], round(d, 4)] for d, b in devs if abs(d) * 100 > pct],
            "starved_beads": sum(1 for b in beads if b.get("starved")),
            "starvations": sum(b.get("starved") or 0 for b in beads)}


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

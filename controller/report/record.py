"""The build record's per-bead and per-layer rows, arc-time cross-checks and CSV (docs/contract.md §7).

Everything here is read from the journal (what the devices measured) and the job (what was
planned); times in the journal are wall-clock seconds, scaled by the run's time scale to process
seconds for arc time, travel speed and waits.
"""
from __future__ import annotations

import csv
import datetime as _dt
from pathlib import Path
from typing import Any, Sequence

from controller.journal.queries import SampleRow
from controller.journal.store import Journal
from core.material import ProcessTolerance
from planner.job import Job, Pass

# One row per planned bead (docs/contract.md §7); every name carries its unit. How each figure is
# measured: docs/build-record.md "Per bead". There is no planned voltage: the job carries none and
# the material has no voltage line (the synergic source sets the voltage from the wire feed); the
# voltage is judged against the material's absolute window, given as voltage_window_*_v.
CSV_COLUMNS = (
    "layer", "pass", "role", "status", "runs",
    "arc_time_s", "motion_time_s", "still_time_s", "still_count", "still_max_s",
    "length_planned_mm", "length_measured_mm",
    "current_planned_a", "current_mean_a", "current_p5_a", "current_p95_a", "current_min_a", "current_max_a",
    "voltage_window_min_v", "voltage_window_max_v",
    "voltage_mean_v", "voltage_p5_v", "voltage_p95_v", "voltage_min_v", "voltage_max_v",
    "wfs_planned_m_min", "wfs_mean_m_min", "wfs_p5_m_min", "wfs_p95_m_min", "wfs_min_m_min", "wfs_max_m_min",
    "speed_planned_mm_min", "speed_planned_min_mm_min", "speed_planned_max_mm_min", "speed_measured_mm_min",
    "starved_count", "heat_input_j_mm", "defects_count",
    "defect_reasons",
)
ARC_TIME_TOLERANCE = 0.02  # the three arc-time figures must agree within 2 %


def iso(t: float | None) -> str | None:
    """A Unix time as an ISO 8601 UTC string."""
    if t is None:
        return None
    return _dt.datetime.fromtimestamp(t, tz=_dt.UTC).isoformat(timespec="seconds")


def _planned(job: Job | None, layer: int, pass_: int) -> Pass | None:
    """The planned pass (None: no job, or a bead the job does not have)."""
    if job is None or not (0 <= layer < len(job.layers)) or not (0 <= pass_ < len(job.layers[layer].passes)):
        return None
    return job.layers[layer].passes[pass_]


def _wfs_stats(samples: list[SampleRow], on: float, off: float, layer: int,
               pass_: int) -> tuple[float | None, float | None, float | None]:
    vals = [s[3] for s in samples if on <= s[0] <= off and s[5] == layer and s[6] == pass_ and s[3] is not None]
    if not vals:
        return None, None, None
    return round(sum(vals) / len(vals), 3), round(min(vals), 3), round(max(vals), 3)


def _r(x: float | None, nd: int = 2) -> float | None:
    return None if x is None else round(float(x), nd)


def _sum(rows: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return sum(vals) if vals else None


def _wmean(rows: list[dict[str, Any]], key: str, weight: str) -> float | None:
    """Mean of `key` over the runs of a bead, weighted by `weight` (arc time)."""
    pairs = [(r[key], r.get(weight) or 0.0) for r in rows if r.get(key) is not None]
    if not pairs:
        return None
    w = sum(x for _, x in pairs)
    mean: float = sum(v * x for v, x in pairs) / w if w > 0 else sum(v for v, _ in pairs) / len(pairs)
    return mean


def _ext(rows: list[dict[str, Any]], key: str, fn: Any) -> float | None:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return fn(vals) if vals else None


def _bead_run(b: dict[str, Any], plan: Pass | None, scale: float, samples: list[SampleRow]) -> dict[str, Any]:
    """One journaled bead row (one run of a planned bead) in the record's units."""
    if b.get("wfs_min") is not None:   # every bus cycle of the bead (the samples are thinned)
        w_mean, w_min, w_max = b["wfs_mean"], b["wfs_min"], b["wfs_max"]
    else:
        w_mean, w_min, w_max = _wfs_stats(samples, b["arc_on"], b["arc_off"], b["layer"], b["pass"])
        w_mean = w_mean if w_mean is not None else b["wfs_mean"]
    # arc time: the source's arc stable while the torch moved (bead_measure.Pace.arc_time); a
    # journal from before it was measured gives the source's whole arc-on span instead
    arc = b.get("arc_s")
    if arc is None:
        arc = max(0.0, b["arc_off"] - b["arc_on"]) * scale
    return {"run": b["run"], "interrupted": bool(b["interrupted"]), "arc_s": arc, "motion_s": b.get("motion_s"),
            "still_s": b.get("still_s"), "still_n": b.get("still_n"), "still_max_s": b.get("still_max_s"),
            "slowed_n": b.get("slowed_n"),
            "length_mm": b["length_mm"], "i_mean": b["i_mean"], "i_min": b["i_min"], "i_max": b["i_max"],
            "i_p5": b.get("i_p5"), "i_p95": b.get("i_p95"), "u_mean": b["u_mean"], "u_min": b["u_min"],
            "u_max": b["u_max"], "u_p5": b.get("u_p5"), "u_p95": b.get("u_p95"), "w_mean": w_mean,
            "w_min": w_min, "w_max": w_max, "w_p5": b.get("wfs_p5"), "w_p95": b.get("wfs_p95"),
            "speed": b.get("speed_actual_mm_min"), "starved": b.get("starved"), "heat": b["heat_input_j_mm"],
            # the speed the bead was commanded at: the plan's, or the layer control's trim of it
            "speed_plan": b["speed_mm_min"] or (plan.speed_mm_min if plan is not None else None)}


def _bead_keys(job: Job | None, runs: dict[tuple[int, int], list[dict[str, Any]]]) -> list[tuple[int, int]]:
    """(layer, pass) of every bead to report: each pass of the job, else each journaled bead."""
    if job:
        return [(li, pi) for li, la in enumerate(job.layers) for pi in range(len(la.passes))]
    return sorted(runs)


def _bead_speed(rows: list[dict[str, Any]], motion: Any, length: Any) -> Any:
    """The pace the device kept while depositing (mm/min): length over motion time, else the one run's."""
    speed = None
    if motion and length:
        speed = length / motion * 60.0         # the pace the device kept while depositing
    elif len(rows) == 1:
        speed = rows[0]["speed"]
    return speed


def _bead_status(key: tuple[int, int], done: Any, rows: list[dict[str, Any]], mine: list[dict[str, Any]]) -> str:
    """done, defect (done with a defect), interrupted (some runs, not done) or not built."""
    status = "done" if key in done else ("interrupted" if rows else "not built")
    if mine and status == "done":
        status = "defect"
    return status


def bead_records(journal: Journal, job: Job | None, scale: float, defects: list[dict[str, Any]],
                 tolerance: ProcessTolerance | None = None) -> list[dict[str, Any]]:
    """One record per planned bead (every pass of the job, built or not): planned against measured.

    A bead deposited in several runs (cut by a stop, finished by `cell resume`) is one row: its
    lengths and times add up, its means are weighted by arc time, its extremes and percentiles
    are the widest of the runs. Without the job (a journal alone), one row per journaled bead."""
    samples = journal.sample_rows()
    runs: dict[tuple[int, int], list[dict[str, Any]]] = {}
    for b in journal.bead_rows():
        key = (b["layer"], b["pass"])
        s = journal.run_time_scale(b["run"]) or scale
        runs.setdefault(key, []).append(_bead_run(b, _planned(job, *key), s, samples))
    keys = _bead_keys(job, runs)
    done = journal.done_passes()
    out = []
    for la, pa in keys:
        plan = _planned(job, la, pa)
        rows = runs.get((la, pa), [])
        mine = [d for d in defects if d.get("layer") == la and d.get("pass") == pa]
        arc = _sum(rows, "arc_s")
        motion = _sum(rows, "motion_s")
        length = _sum(rows, "length_mm")
        speed = _bead_speed(rows, motion, length)
        i_mean, u_mean = _wmean(rows, "i_mean", "arc_s"), _wmean(rows, "u_mean", "arc_s")
        status = _bead_status((la, pa), done, rows, mine)
        out.append({
            "layer": la, "pass": pa, "role": plan.role if plan else None, "status": status,
            "runs": "+".join(str(r["run"]) for r in rows),
            "arc_time_s": _r(arc, 3), "motion_time_s": _r(motion, 3),
            "still_time_s": _r(_sum(rows, "still_s"), 3), "still_count": _sum(rows, "still_n"),
            "still_max_s": _r(_ext(rows, "still_max_s", max), 3),
            "slowed_count": _sum(rows, "slowed_n"),   # report.json only: M4 slow-downs (docs/laser-power.md)
            "length_planned_mm": _r(_polyline_mm(plan.points.tolist()), 2) if plan else None,
            "length_measured_mm": _r(length, 2),
            "current_planned_a": plan.current_a if plan else None, "current_mean_a": _r(i_mean),
            "current_p5_a": _r(_ext(rows, "i_p5", min)), "current_p95_a": _r(_ext(rows, "i_p95", max)),
            "current_min_a": _r(_ext(rows, "i_min", min)), "current_max_a": _r(_ext(rows, "i_max", max)),
            "voltage_window_min_v": tolerance.voltage_min_v if tolerance is not None else None,
            "voltage_window_max_v": tolerance.voltage_max_v if tolerance is not None else None,
            "voltage_mean_v": _r(u_mean),
            "voltage_p5_v": _r(_ext(rows, "u_p5", min)), "voltage_p95_v": _r(_ext(rows, "u_p95", max)),
            "voltage_min_v": _r(_ext(rows, "u_min", min)), "voltage_max_v": _r(_ext(rows, "u_max", max)),
            "wfs_planned_m_min": plan.wfs_m_min if plan else None, "wfs_mean_m_min": _r(_wmean(rows, "w_mean", "arc_s"), 3),
            "wfs_p5_m_min": _r(_ext(rows, "w_p5", min), 3), "wfs_p95_m_min": _r(_ext(rows, "w_p95", max), 3),
            "wfs_min_m_min": _r(_ext(rows, "w_min", min), 3), "wfs_max_m_min": _r(_ext(rows, "w_max", max), 3),
            # the plan's speed: its length-weighted mean, and the range of its segments' (cell-job/2)
            "speed_planned_mm_min": _r(plan.speed_mm_min, 1) if plan else (rows[0]["speed_plan"] if rows else None),
            "speed_planned_min_mm_min": _r(float(plan.speeds().min()), 1) if plan else None,
            "speed_planned_max_mm_min": _r(float(plan.speeds().max()), 1) if plan else None,
            "speed_measured_mm_min": _r(speed, 1),
            "starved_count": _sum(rows, "starved"),
            "heat_input_j_mm": _r(_wmean(rows, "heat", "length_mm")),
            "defects_count": len(mine),
            "defect_reasons": "; ".join(str(d.get("message")) for d in mine),
        })
    return out


def layer_records(journal: Journal, job: Job | None, scale: float) -> list[dict[str, Any]]:
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
        ip = job.layers[la].interpass if job and 0 <= la < len(job.layers) else None
        limit = ip.max_temperature_c if ip is not None else None
        out.append({"layer": la, "start": iso(t0), "interpass_temperature_c": _r(before[-1], 1) if before else None,
                    "interpass_limit_c": limit,
                    "wait_s": round((t0 - prev_end) * scale, 1) if prev_end is not None else None})
        prev_end = last[la]
    return out


def _polyline_mm(points: list[Sequence[float]]) -> float:
    length: float = sum(sum((b - a) ** 2 for a, b in zip(p, q)) ** 0.5 for p, q in zip(points, points[1:]))
    return length


def planned_arc_s(job: Job | None, beads: list[dict[str, Any]]) -> float:
    """The plan's arc time of the passes these beads belong to (whole passes, planned speed)."""
    if not job:
        return 0.0
    total = 0.0
    for b in beads:
        if b.get("status") == "not built":
            continue
        p = _planned(job, b["layer"], b["pass"])
        if p is not None and p.speed_mm_min:
            total += p.arc_time_s   # each segment at its own speed (cell-job/2)
    return total


def _planned_s_per_mm(job: Job | None, b: dict[str, Any]) -> float | None:
    """Planned arc seconds per mm of a bead: its plan's arc time over its length (a cell-job/2
    pass's segments each at their own speed), else 60 / its planned speed."""
    p = _planned(job, b["layer"], b["pass"]) if job else None
    if p is not None and p.per_segment and p.length_mm > 0:
        return p.arc_time_s / p.length_mm
    return 60.0 / b["speed_planned_mm_min"] if b.get("speed_planned_mm_min") else None


def arc_time_figures(journal: Journal, job: Job | None, scale: float, beads: list[dict[str, Any]]) -> dict[str, Any]:
    """Three arc times that must agree within 2 %, and the measured arc time beside them.

    plan_s: the job's passes that were built, at their planned length and speed (the figure
    `cell plan` and the demo print); planned_s: the length each bead actually deposited (device
    progress reports with the arc stable), at its planned speed; measured_s: that length at the
    speed the device actually kept. arc_on_s: the sum of the beads' arc time (the source's arc
    stable while the torch moved, from the release to the last move: bead_measure.Pace.arc_time),
    which the simulators' deposit log confirms; it exceeds measured_s by the time the torch stood
    still with the arc on (`arc_on_excess_per_bead_s`).
    """
    del journal
    plan = planned_arc_s(job, beads)
    built = [b for b in beads if b.get("status") != "not built"]
    planned = sum((b["length_measured_mm"] or 0.0) * (_planned_s_per_mm(job, b) or 0.0) for b in built)
    measured = sum(b["motion_time_s"] for b in built if b.get("motion_time_s") is not None)
    arc_on = sum(b["arc_time_s"] or 0.0 for b in built)
    figs: dict[str, Any] = {"plan_s": round(plan, 1), "planned_s": round(planned, 1),
                            "measured_s": round(measured, 1), "arc_on_s": round(arc_on, 1)}
    vals = [v for v in (plan, planned, measured) if v > 0]
    spread = (max(vals) - min(vals)) / max(vals) if vals else 0.0
    figs["spread"] = round(spread, 4)
    figs["agree"] = spread <= ARC_TIME_TOLERANCE and len(vals) == 3
    n = sum(1 for b in built if b.get("motion_time_s") is not None)
    figs["arc_on_excess_per_bead_s"] = round((arc_on - measured) / n, 3) if n else None
    figs["bus_cycle_process_s"] = round(0.010 * scale, 3)
    if not figs["agree"]:
        figs["note"] = ("arc times disagree by more than 2 %: beads short of their plan, or travel speed "
                        "differs from plan (see length_measured_mm and speed_measured_mm_min per bead)")
    return figs


def _speed_tolerance_pct(job: Job | None) -> float:
    """The material's `tolerance.speed_pct` of the job (10 % when it has none or a bad one)."""
    try:
        pct = float((job.material if job else {}).get("tolerance", {}).get("speed_pct", 10.0))
    except (AttributeError, TypeError, ValueError):
        pct = 10.0
    return pct


def _speed_deviations(beads: list[dict[str, Any]], job: Job | None = None) -> list[tuple[float, dict[str, Any]]]:
    """(measured / planned speed - 1, bead) of each bead with both speeds. A cell-job/2 bead's
    measured speed is its pace against the plan's own per-segment timing, as one speed (its length
    over its planned arc time: bead_measure.Pace), and is compared with that."""
    out = []
    for b in beads:
        if not (b.get("speed_measured_mm_min") and b.get("speed_planned_mm_min")):
            continue
        s_per_mm = _planned_s_per_mm(job, b)
        planned = 60.0 / s_per_mm if s_per_mm else b["speed_planned_mm_min"]
        out.append((b["speed_measured_mm_min"] / planned - 1.0, b))
    return out


def travel_speed_summary(beads: list[dict[str, Any]], job: Job | None = None) -> dict[str, Any]:
    """How far the measured travel speed strayed from the plan, the beads outside the material's
    `tolerance.speed_pct` (flagged, not defects), the starved beads and the stand-stills."""
    pct = _speed_tolerance_pct(job)
    devs = _speed_deviations(beads, job)
    worst = max((d for d, _ in devs), key=abs) if devs else None
    return {"beads_measured": len(devs), "worst_deviation": _r(worst, 4),
            "within_2pct": bool(devs) and all(abs(d) <= 0.02 for d, _ in devs),
            "tolerance_pct": pct,
            "off_speed_beads": [[b["layer"], b["pass"], round(d, 4)] for d, b in devs if abs(d) * 100 > pct],
            "starved_beads": sum(1 for b in beads if b.get("starved_count")),
            "starvations": sum(b.get("starved_count") or 0 for b in beads),
            "still_beads": sum(1 for b in beads if b.get("still_count")),
            "still_s": round(sum(b.get("still_time_s") or 0.0 for b in beads), 3)}


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

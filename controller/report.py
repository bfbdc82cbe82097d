"""Build report: a JSON summary and PNG plots, from the journal alone (DESIGN.md §6).

Plots (matplotlib, Agg): per-layer arc time and heat input, current/voltage traces, part
temperature, and a map of the defects (arc losses, interlock stops) over the planned paths.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from controller.journal import Journal

ALARM_KINDS = ("alarm",)


def summarize(journal: Journal, job: dict | None = None, state: str | None = None) -> dict[str, Any]:
    """The build's summary as a JSON-ready dict (times in process seconds)."""
    meta = journal.job() or {}
    scale = 1.0
    for (msg,) in journal.query("SELECT message FROM events WHERE kind='run' ORDER BY id DESC LIMIT 1"):
        scale = float(json.loads(msg).get("time_scale", 1.0))
    layers_total = len(job["layers"]) if job else None
    passes_total = sum(len(la["passes"]) for la in job["layers"]) if job else None
    done = {(la, pa) for la, pa, st in journal.query(
        "SELECT layer, pass, state FROM passes WHERE id IN (SELECT max(id) FROM passes GROUP BY layer, pass)"
    ) if st == "done"}
    layers_done = 0
    if job:
        for li, la in enumerate(job["layers"]):
            if all((li, pi) in done for pi in range(len(la["passes"]))):
                layers_done += 1
            else:
                break
    beads = journal.query(
        "SELECT layer, pass, run, arc_on, arc_off, length_mm, i_mean, u_mean, wfs_mean, heat_input_j_mm, interrupted"
        " FROM beads ORDER BY id"
    )
    per_layer: dict[int, dict[str, float]] = {}
    for layer, _p, _r, on, off, length, _i, _u, _w, hi, _int in beads:
        d = per_layer.setdefault(layer, {"arc_time_s": 0.0, "heat_j": 0.0, "length_mm": 0.0})
        d["arc_time_s"] += max(0.0, off - on) * scale
        d["length_mm"] += length
        d["heat_j"] += (hi or 0.0) * length
    alarms = [
        {"t": t, "message": msg, "state": st, "layer": la, "pass": pa,
         "position": [x, y, z] if x is not None else None, "run": run}
        for t, msg, st, la, pa, x, y, z, run in journal.query(
            "SELECT t, message, state, layer, pass, x, y, z, run FROM events WHERE kind='alarm' ORDER BY id")
    ]
    defects = [a for a in alarms if a["position"] is not None]
    state_row = [(state,)] if state else journal.query(
        "SELECT state FROM events WHERE kind='transition' AND state NOT IN ('disconnected', 'idle')"
        " ORDER BY id DESC LIMIT 1")
    runs = journal.query("SELECT count(DISTINCT run) FROM events")[0][0]
    arc_starts = journal.query("SELECT count(*) FROM passes WHERE state='arc_on'")[0][0]
    return {
        "job": {"name": meta.get("name"), "hash": meta.get("hash"), "platform": meta.get("platform")},
        "state": state_row[0][0] if state_row else None,
        "layers_total": layers_total,
        "passes_total": passes_total,
        "layers_done": layers_done,
        "passes_done": len(done),
        "arc_starts": arc_starts,
        "runs": runs,
        "time_scale": scale,
        "arc_time_s": round(sum(d["arc_time_s"] for d in per_layer.values()), 3),
        "deposit_length_mm": round(sum(d["length_mm"] for d in per_layer.values()), 2),
        "per_layer": [
            {"layer": k, "arc_time_s": round(v["arc_time_s"], 3), "length_mm": round(v["length_mm"], 2),
             "heat_input_j_mm": round(v["heat_j"] / v["length_mm"], 2) if v["length_mm"] else None}
            for k, v in sorted(per_layer.items())
        ],
        "alarms": alarms,
        "defects": defects,
    }


def write_report(journal: Journal, out_dir: str | Path, job: dict | None = None, plots: bool = True,
                 state: str | None = None) -> Path:
    """Write report.json (and the PNGs) into `out_dir`; returns the path of report.json."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(journal, job, state)
    pngs = _plots(journal, out, job, summary) if plots else []
    summary["plots"] = [p.name for p in pngs]
    path = out / "report.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def _plots(journal: Journal, out: Path, job: dict | None, summary: dict) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths: list[Path] = []
    pl = summary["per_layer"]
    fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    ax[0].bar([d["layer"] + 1 for d in pl], [d["arc_time_s"] for d in pl], color="tab:blue")
    ax[0].set_ylabel("arc time [s]")
    ax[1].bar([d["layer"] + 1 for d in pl], [d["heat_input_j_mm"] or 0 for d in pl], color="tab:red")
    ax[1].set_ylabel("heat input [J/mm]")
    ax[1].set_xlabel("layer")
    fig.suptitle("Per-layer arc time and heat input")
    paths.append(_save(fig, out / "layers.png"))

    rows = journal.query("SELECT t, current_a, voltage_v, wfs_m_min, temperature_c FROM samples ORDER BY t")
    t0 = rows[0][0] if rows else 0.0
    scale = summary.get("time_scale") or 1.0
    t = [(r[0] - t0) * scale for r in rows]  # process time
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    ax[0].plot(t, [r[1] for r in rows], lw=0.6, color="tab:orange")
    ax[0].set_ylabel("current [A]")
    ax[1].plot(t, [r[2] for r in rows], lw=0.6, color="tab:green")
    ax[1].set_ylabel("voltage [V]")
    ax[1].set_xlabel("time [s]")
    fig.suptitle("Current and voltage")
    paths.append(_save(fig, out / "process.png"))

    fig, ax = plt.subplots(figsize=(10, 4))
    ax.plot(t, [r[4] for r in rows], lw=0.8, color="tab:red")
    ax.set_ylabel("part temperature [°C]")
    ax.set_xlabel("time [s]")
    paths.append(_save(fig, out / "temperature.png"))

    fig, ax = plt.subplots(figsize=(7, 7))
    if job:
        for li, la in enumerate(job["layers"]):
            if li % max(1, len(job["layers"]) // 5):
                continue  # a few layers suffice for the outline
            for pa in la["passes"]:
                xs = [p[0] for p in pa["points"]]
                ys = [p[1] for p in pa["points"]]
                ax.plot(xs, ys, lw=0.4, color="0.7")
    for d in summary["defects"]:
        x, y, _z = d["position"]
        ax.plot([x], [y], "x", color="red", ms=10, mew=2)
        lab = f"L{d['layer'] + 1}" if d["layer"] is not None else ""
        ax.annotate(lab, (x, y), textcoords="offset points", xytext=(5, 5), color="red")
    ax.set_aspect("equal")
    ax.set_title(f"Defects: {len(summary['defects'])}")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    paths.append(_save(fig, out / "defects.png"))
    return paths


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path

"""The build record's plots (matplotlib, Agg): per-layer bars, process traces, temperature, defects.

Traces are drawn in process time with gaps left open (a pause or a resume is a break in the line,
not a straight segment), layer starts marked, wire feed beside current and voltage, and the
interpass limit drawn on the temperature.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from controller.journal.store import Journal

GAP_FACTOR = 20.0  # a sample interval this many times the median breaks the line


def _with_gaps(t: list[float], cols: list[list[Any]]) -> tuple[list[float], list[list[Any]]]:
    """Insert a NaN where the sampling stopped, so the gap shows instead of a straight line."""
    if len(t) < 3:
        return t, cols
    dts = sorted(b - a for a, b in zip(t, t[1:]))
    limit = max(dts[len(dts) // 2] * GAP_FACTOR, 1e-9)
    tt: list[float] = [t[0]]
    cc: list[list[Any]] = [[c[0]] for c in cols]
    for i in range(1, len(t)):
        if t[i] - t[i - 1] > limit:
            tt.append(float("nan"))
            for c in cc:
                c.append(float("nan"))
        tt.append(t[i])
        for c, src in zip(cc, cols):
            c.append(src[i] if src[i] is not None else float("nan"))
    return tt, cc


def plot_report(journal: Journal, out: Path, job: dict | None, summary: dict) -> list[Path]:
    """Write layers.png, process.png, temperature.png and defects.png into `out`."""
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

    rows = journal.sample_rows()
    t0 = rows[0][0] if rows else 0.0
    scale = summary.get("time_scale") or 1.0
    t = [(r[0] - t0) * scale for r in rows]
    tt, (cur, volt, wfs, temp) = _with_gaps(t, [[r[1] for r in rows], [r[2] for r in rows],
                                                 [r[3] for r in rows], [r[4] for r in rows]])
    marks = _layer_marks(rows, t)
    fig, ax = plt.subplots(3, 1, figsize=(12, 8), sharex=True)
    for a, ys, lab, col in ((ax[0], cur, "current [A]", "tab:orange"), (ax[1], volt, "voltage [V]", "tab:green"),
                            (ax[2], wfs, "wire feed [m/min]", "tab:purple")):
        a.plot(tt, ys, lw=0.6, color=col)
        a.set_ylabel(lab)
        for x in marks:
            a.axvline(x, color="0.8", lw=0.5, zorder=0)
    ax[2].set_xlabel("process time [s] (grey lines: layer starts; breaks: pauses and resumes)")
    fig.suptitle("Current, voltage and wire feed")
    paths.append(_save(fig, out / "process.png"))

    fig, ax = plt.subplots(figsize=(12, 4))
    ax.plot(tt, temp, lw=0.8, color="tab:red", label="part temperature")
    limits = [la.get("interpass_limit_c") for la in summary.get("layers", []) if la.get("interpass_limit_c")]
    if limits:
        ax.axhline(max(limits), color="k", ls="--", lw=0.8, label=f"interpass limit {max(limits):.0f} °C")
    for x in marks:
        ax.axvline(x, color="0.85", lw=0.5, zorder=0)
    ax.set_ylabel("part temperature [°C]")
    ax.set_xlabel("process time [s]")
    ax.legend(loc="upper right")
    paths.append(_save(fig, out / "temperature.png"))
    paths.append(_defects(plt, out, job, summary))
    return paths


def _layer_marks(rows: list[tuple], t: list[float]) -> list[float]:
    marks, seen = [], set()
    for r, x in zip(rows, t):
        if r[5] is not None and r[5] not in seen:
            seen.add(r[5])
            marks.append(x)
    return marks


def _defects(plt: Any, out: Path, job: dict | None, summary: dict) -> Path:
    fig, ax = plt.subplots(figsize=(7, 7))
    if job:
        for li, la in enumerate(job["layers"]):
            if li % max(1, len(job["layers"]) // 5):
                continue  # a few layers suffice for the outline
            for pa in la["passes"]:
                ax.plot([p[0] for p in pa["points"]], [p[1] for p in pa["points"]], lw=0.4, color="0.7")
    for d in summary["defects"]:
        x, y, _z = d["position"]
        ax.plot([x], [y], "x", color="red", ms=10, mew=2)
        lab = f"L{d['layer'] + 1}" if d["layer"] is not None else ""
        ax.annotate(lab, (x, y), textcoords="offset points", xytext=(5, 5), color="red")
    ax.set_aspect("equal")
    ax.set_title(f"Defects: {len(summary['defects'])}")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    return _save(fig, out / "defects.png")


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path

"""The build record's plots (matplotlib, Agg): per-layer bars, process traces, temperature, defects.

Traces are drawn in process time with gaps left open (a pause or a resume is a break in the line,
not a straight segment), layer starts marked, wire feed beside current and voltage, and the
interpass limit drawn on the temperature.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from controller.journal.queries import SampleRow
from controller.journal.store import Journal
from controller.report.figures import new_figure, save
from planner.job import Job

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


def plot_report(journal: Journal, out: Path, job: Job | None, summary: dict[str, Any]) -> list[Path]:
    """Write layers.png, process.png, temperature.png and defects.png into `out`."""
    paths: list[Path] = []
    pl = summary["per_layer"]
    fig, ax = new_figure(2, 1, (8, 6), sharex=True)
    ax[0].bar([d["layer"] + 1 for d in pl], [d["arc_time_s"] for d in pl], color="tab:blue")
    ax[0].set_ylabel("arc time [s]")
    ax[1].bar([d["layer"] + 1 for d in pl], [d["heat_input_j_mm"] or 0 for d in pl], color="tab:red")
    ax[1].set_ylabel("heat input [J/mm]")
    ax[1].set_xlabel("layer")
    fig.suptitle("Per-layer arc time and heat input")
    paths.append(save(fig, out / "layers.png"))

    rows = journal.sample_rows()
    t0 = rows[0][0] if rows else 0.0
    scale = summary.get("time_scale") or 1.0
    t = [(r[0] - t0) * scale for r in rows]
    tt, (temp,) = _with_gaps(t, [[r[4] for r in rows]])
    marks = _layer_marks(rows, t)
    paths.append(_process_per_bead(out, summary))
    fig, ax = new_figure(1, 1, (12, 4))
    ax.plot(tt, temp, lw=0.8, color="tab:red", label="part temperature")
    limits = [la.get("interpass_limit_c") for la in summary.get("layers", []) if la.get("interpass_limit_c")]
    if limits:
        ax.axhline(max(limits), color="k", ls="--", lw=0.8, label=f"interpass limit {max(limits):.0f} °C")
    for x in marks:
        ax.axvline(x, color="0.85", lw=0.5, zorder=0)
    ax.set_ylabel("part temperature [°C]")
    ax.set_xlabel("process time [s]")
    ax.legend(loc="upper right")
    paths.append(save(fig, out / "temperature.png"))
    paths.append(_defects(out, job, summary))
    return paths


# (signal, mean, p5, p95, min, max, planned, label, colour) per panel of process.png
_SIGNALS = (
    ("current", "current_mean_a", "current_p5_a", "current_p95_a", "current_min_a", "current_max_a",
     "current_planned_a", "current [A]", "tab:orange"),
    ("voltage", "voltage_mean_v", "voltage_p5_v", "voltage_p95_v", "voltage_min_v", "voltage_max_v",
     None, "voltage [V]", "tab:green"),
    ("wfs", "wfs_mean_m_min", "wfs_p5_m_min", "wfs_p95_m_min", "wfs_min_m_min", "wfs_max_m_min",
     "wfs_planned_m_min", "wire feed [m/min]", "tab:purple"),
    ("speed", "speed_measured_mm_min", None, None, None, None, "speed_planned_mm_min", "travel speed [mm/min]",
     "tab:blue"),
)


def _process_per_bead(out: Path, summary: dict[str, Any]) -> Path:
    """process.png: per bead (x: beads in build order), each signal's mean (dot) and 5-95 %
    spread (bar), min/max (thin ticks), against the plan (black steps) and its tolerance band
    (grey); beads with a defect shaded red, layer starts as grey lines: the weld-monitoring view
    of a build, bead by bead, instead of a trace over hours."""
    beads = [b for b in summary.get("beads", []) if b.get("status") != "not built"]
    tol = summary.get("tolerance") or {}
    n = len(beads)
    x = list(range(1, n + 1))
    fig, axes = new_figure(len(_SIGNALS), 1, (max(10.0, min(24.0, 6 + n * 0.06)), 11), sharex=True)
    layer_starts = [i + 1 for i, b in enumerate(beads) if i == 0 or b["layer"] != beads[i - 1]["layer"]]
    bad = [i + 1 for i, b in enumerate(beads) if b.get("defects_count")]
    pct = {"current": tol.get("current_pct"), "wfs": tol.get("wfs_pct"), "speed": tol.get("speed_pct")}
    for ax, signal in zip(axes, _SIGNALS):
        _bead_panel(ax, signal, beads, x, bad, layer_starts, pct, tol)
    axes[-1].set_xlabel("bead (in build order; grey lines: layer starts; red: beads with a defect)")
    axes[-1].set_xlim(0.5, max(n, 1) + 0.5)
    # lazy: matplotlib loads only when this path runs (start-up time)
    from matplotlib.ticker import MaxNLocator

    axes[-1].xaxis.set_major_locator(MaxNLocator(integer=True))
    fig.suptitle(f"Process per bead: {n} beads, {len(bad)} with a defect")
    return save(fig, out / "process.png")


def _bead_panel(ax: Any, signal: tuple[Any, ...], beads: list[dict[str, Any]], x: list[int], bad: list[int],
                layer_starts: list[int], pct: dict[str, Any], tol: dict[str, Any]) -> None:
    """One signal's panel of process.png: defect shading, layer starts, plan and band, the measured."""
    name, mean, p5, p95, lo, hi, plan, label, colour = signal
    for xb in bad:
        ax.axvspan(xb - 0.5, xb + 0.5, color="red", alpha=0.15, lw=0, zorder=0)
    for xl in layer_starts[1:]:
        ax.axvline(xl - 0.5, color="0.85", lw=0.6, zorder=0)
    _plan_and_band(ax, name, plan, beads, x, pct, tol)
    _bead_means(ax, beads, x, mean, p5, p95, lo, hi, colour)
    if bad:
        _defect_marks(ax, beads, bad, mean)
    ax.set_ylabel(label)
    ax.legend(loc="upper right", fontsize=7, ncol=5, framealpha=0.7)


def _plan_and_band(ax: Any, name: str, plan: str | None, beads: list[dict[str, Any]], x: list[int],
                   pct: dict[str, Any], tol: dict[str, Any]) -> None:
    """The plan as black steps with its ± tolerance band, or the voltage window (no planned voltage)."""
    if plan is not None:
        ps = [b.get(plan) for b in beads]
        ax.step(x, [float("nan") if v is None else v for v in ps], where="mid", color="k", lw=0.8,
                label="plan")
        band = pct.get(name)
        if band:
            f = float(band) / 100.0
            ax.fill_between(x, [float("nan") if v is None else v * (1 - f) for v in ps],
                            [float("nan") if v is None else v * (1 + f) for v in ps], step="mid",
                            color="0.6", alpha=0.25, lw=0, label=f"±{band:g} %")
    elif name == "voltage" and tol.get("voltage_min_v") is not None:
        ax.axhspan(tol["voltage_min_v"], tol["voltage_max_v"], color="0.6", alpha=0.15, lw=0,
                   label=f"window {tol['voltage_min_v']:g}-{tol['voltage_max_v']:g} V")


def _bead_means(ax: Any, beads: list[dict[str, Any]], x: list[int], mean: str, p5: str | None, p95: str | None,
                lo: str | None, hi: str | None, colour: str) -> None:
    """Each bead's mean: with its 5-95 % spread and min/max ticks where the signal has them."""
    ys = [b.get(mean) for b in beads]
    xs = [xi for xi, y in zip(x, ys) if y is not None]
    ym = [y for y in ys if y is not None]
    if p5 is not None:
        _spread_bars(ax, beads, ys, xs, ym, p5, p95, colour)
        _min_max_ticks(ax, beads, xs, mean, lo, hi, colour)
    else:
        ax.plot(xs, ym, "o", ms=2.5, color=colour, label="measured")


def _field(bead: dict[str, Any], key: str | None) -> Any:
    """The bead's value under `key`; None where the signal has no such field (key None)."""
    return None if key is None else bead.get(key)


def _spread_bars(ax: Any, beads: list[dict[str, Any]], ys: list[Any], xs: list[int], ym: list[Any], p5: str,
                 p95: str | None, colour: str) -> None:
    """The means as dots with their 5-95 % spread as error bars."""
    lo_err = [max(0.0, y - (b.get(p5) if b.get(p5) is not None else y)) for b, y in zip(beads, ys) if y is not None]
    hi_err = [max(0.0, (_field(b, p95) if _field(b, p95) is not None else y) - y) for b, y in zip(beads, ys)
              if y is not None]
    ax.errorbar(xs, ym, yerr=[lo_err, hi_err], fmt="o", ms=2.5, color=colour, ecolor=colour, elinewidth=1.2,
                capsize=0, label="mean, 5-95 %")


def _min_max_ticks(ax: Any, beads: list[dict[str, Any]], xs: list[int], mean: str, lo: str | None, hi: str | None,
                   colour: str) -> None:
    """Each measured bead's min and max as thin ticks."""
    mins = [_field(b, lo) for b in beads if b.get(mean) is not None]
    maxs = [_field(b, hi) for b in beads if b.get(mean) is not None]
    ax.plot(xs, [float("nan") if v is None else v for v in mins], "_", color=colour, ms=4, alpha=0.6,
            label="min / max")
    ax.plot(xs, [float("nan") if v is None else v for v in maxs], "_", color=colour, ms=4, alpha=0.6)


def _defect_marks(ax: Any, beads: list[dict[str, Any]], bad: list[int], mean: str) -> None:
    """A red cross on the mean of each bead with a defect."""
    yd = [b.get(mean) for b in beads if b.get("defects_count")]
    xd = [xb for xb, y in zip(bad, yd) if y is not None]
    ax.plot(xd, [y for y in yd if y is not None], "x", color="red", ms=6, mew=1.5, label="defect")


def _layer_marks(rows: list[SampleRow], t: list[float]) -> list[float]:
    marks, seen = [], set()
    for r, x in zip(rows, t):
        if r[5] is not None and r[5] not in seen:
            seen.add(r[5])
            marks.append(x)
    return marks


def _defects(out: Path, job: Job | None, summary: dict[str, Any]) -> Path:
    fig, ax = new_figure(1, 1, (7, 7))
    if job:
        for li, la in enumerate(job.layers):
            if li % max(1, len(job.layers) // 5):
                continue  # a few layers suffice for the outline
            for pa in la.passes:
                ax.plot(pa.points[:, 0], pa.points[:, 1], lw=0.4, color="0.7")
    for d in summary["defects"]:
        x, y, _z = d["position"]
        ax.plot([x], [y], "x", color="red", ms=10, mew=2)
        lab = f"L{d['layer'] + 1}" if d["layer"] is not None else ""
        ax.annotate(lab, (x, y), textcoords="offset points", xytext=(5, 5), color="red")
    ax.set_aspect("equal")
    ax.set_title(f"Defects: {len(summary['defects'])}")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    return save(fig, out / "defects.png")

"""Was a bead deposited as planned? The devices' measurements decide (docs/contract.md §6, issue 13).

A pass is done only when its last move was executed (the robot's EXE / grbl's sync point), the
arc was stable all along, and the measured current, voltage and wire feed stayed within the
material's tolerance (`tolerance:` of config/materials/*.yaml) of the plan. Anything else is a
defect: journaled with its position and reported, never silently "done".
"""
from __future__ import annotations

import math

from core.material import ProcessTolerance


def judge(stats: dict[str, float | None], planned_i: float, planned_wfs: float | tuple[float, float], tol: ProcessTolerance,
          arc_faltered: bool, planned_speed: float | None = None) -> str | None:
    """None for a good bead, else the reason it is a defect (one line).

    `planned_wfs` is the pass's wire feed, or (cell-job/2) the lowest and highest of its segments':
    the measured wire feed is judged against that range ± the tolerance, and the current, which a
    synergic source sets from the wire feed, against the set-point scaled by the same range
    (docs/along-the-path.md)."""
    if arc_faltered:
        return "arc not stable all along the bead"
    if not stats or stats.get("i_mean") is None:
        return "no measurement while the arc burned"
    out = []
    starved = stats.get("starved") or 0
    if starved > 0:
        # the robot's queue ran empty with the arc on: the torch stopped on the bead (a blob)
        out.append(f"motion queue ran empty {starved:g} time(s) inside the bead")
    still = stats.get("still_n") or 0
    if still > 0:
        # the device's progress reports show the torch standing still with the arc on for longer
        # than one bus cycle (controller/runtime/bead_measure.py Pace.standstill)
        out.append(f"torch stood still with the arc on {still:g} time(s), {stats.get('still_s') or 0:.2f} s in "
                   f"total (longest {stats.get('still_max_s') or 0:.2f} s)")
    # The measured travel speed is not judged here: it is timed from EXE arrivals, and at a high
    # time scale on a loaded host their jitter (k x a few ms of process time) would make false
    # defects. The record flags beads outside `tolerance.speed_pct` instead (travel_speed).
    del planned_speed
    wl, wh = planned_wfs if isinstance(planned_wfs, tuple) else (planned_wfs, planned_wfs)
    w_ref = 0.5 * (wl + wh)
    i_set = f"{planned_i:.1f} A" if wl == wh else f"{planned_i * wl / w_ref:.1f}-{planned_i * wh / w_ref:.1f} A"
    i_lo, i_hi = planned_i * wl / w_ref * (1 - tol.current_pct / 100), planned_i * wh / w_ref * (1 + tol.current_pct / 100)
    i_min, i_max = _span(stats, "i", "i_mean")
    if i_min < i_lo or i_max > i_hi:
        out.append(f"current {i_min:.1f}-{i_max:.1f} A outside {i_set} ±{tol.current_pct:g} %")
    w_lo, w_hi = wl * (1 - tol.wfs_pct / 100), wh * (1 + tol.wfs_pct / 100)
    w_min, w_max = _span(stats, "wfs", "wfs_mean")
    w_set = f"{wl:.2f} m/min" if wl == wh else f"{wl:.2f}-{wh:.2f} m/min"
    if w_min < w_lo or w_max > w_hi:
        out.append(f"wire feed {w_min:.2f}-{w_max:.2f} m/min outside {w_set} ±{tol.wfs_pct:g} %")
    u_min, u_max = _span(stats, "u", "u_mean")
    if u_min < tol.voltage_min_v or u_max > tol.voltage_max_v:
        out.append(f"voltage {u_min:.1f}-{u_max:.1f} V outside "
                   f"[{tol.voltage_min_v:g}, {tol.voltage_max_v:g}] V")
    return "; ".join(out) or None


def _span(stats: dict[str, float | None], name: str, mean_key: str) -> tuple[float, float]:
    """A signal's measured (min, max), its mean where the extremes were not reported. A signal never
    measured is ±inf, outside every bound: a bead is good only on what the devices measured."""
    mean = stats.get(mean_key)
    lo, hi = stats.get(f"{name}_min", mean), stats.get(f"{name}_max", mean)
    return (-math.inf if lo is None else lo), (math.inf if hi is None else hi)

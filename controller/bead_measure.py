"""What the devices measured over one bead: the source's current / voltage / wire feed, and the
robot's pace from its EXE reports (DESIGN.md §6: "done" and "deposited" come from the devices).

The travel speed is the least-squares slope of the length reached against the arrival time of
each EXE, over the moves executed with the arc stable. A slope over all the EXEs, rather than
first to last, averages out the jitter of the arrival times: at time scale 120 a 1 ms delay is
0.12 s of process time, a few per cent of a short bead.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class BeadStats:
    """Current / voltage / WFS seen while the arc burned on one bead."""

    arc_on: float = 0.0
    arc_off: float = 0.0
    n: int = 0
    i_sum: float = 0.0
    u_sum: float = 0.0
    w_sum: float = 0.0
    w_min: float = math.inf
    w_max: float = -math.inf
    i_min: float = math.inf
    i_max: float = -math.inf
    u_min: float = math.inf
    u_max: float = -math.inf

    def add(self, i: float, u: float, w: float) -> None:
        self.n += 1
        self.i_sum += i
        self.u_sum += u
        self.w_sum += w
        self.i_min, self.i_max = min(self.i_min, i), max(self.i_max, i)
        self.u_min, self.u_max = min(self.u_min, u), max(self.u_max, u)
        self.w_min, self.w_max = min(self.w_min, w), max(self.w_max, w)

    def as_dict(self) -> dict[str, float | None]:
        if not self.n:
            return {}
        return {"i_mean": self.i_sum / self.n, "i_min": self.i_min, "i_max": self.i_max,
                "u_mean": self.u_sum / self.n, "u_min": self.u_min, "u_max": self.u_max,
                "wfs_mean": self.w_sum / self.n, "wfs_min": self.w_min, "wfs_max": self.w_max}


@dataclass
class Pace:
    """EXE arrivals of one bead: (wall time, length reached along the pass in mm)."""

    t_release: float                      # wall time motion was released (the robot's !GO)
    s_release: float                      # length along the pass where the bead started, mm
    points: list[tuple[float, float]] = field(default_factory=list)
    starved: int = 0                      # times the robot's queue ran empty inside the bead

    def reached(self, t: float, s: float) -> None:
        self.points.append((t, s))

    def speed_mm_s(self) -> float | None:
        """Wall mm/s: the slope over the EXEs (two or more), else from the release to the one EXE."""
        pts = self.points
        if len(pts) >= 2:
            n = len(pts)
            t_mean = sum(t for t, _ in pts) / n
            s_mean = sum(s for _, s in pts) / n
            var = sum((t - t_mean) ** 2 for t, _ in pts)
            if var > 0:
                slope = sum((t - t_mean) * (s - s_mean) for t, s in pts) / var
                if slope > 0:
                    return slope
            t0, s0 = pts[0]
            t1, s1 = pts[-1]
            return (s1 - s0) / (t1 - t0) if t1 > t0 and s1 > s0 else None
        if len(pts) == 1:
            t1, s1 = pts[0]
            dt, ds = t1 - self.t_release, s1 - self.s_release
            return ds / dt if dt > 0 and ds > 0 else None
        return None

    def figures(self, time_scale: float, length_mm: float) -> dict[str, float | int | None]:
        """Actual travel speed (process mm/min), the motion time that deposited `length_mm`
        (process s), the moves counted and the starvations."""
        v = self.speed_mm_s()
        if v is None:
            return {"speed_mm_min": None, "motion_s": None, "moves": len(self.points), "starved": self.starved}
        v_process = v / time_scale                # wall mm/s -> process mm/s
        return {"speed_mm_min": v_process * 60.0, "motion_s": length_mm / v_process if length_mm > 0 else 0.0,
                "moves": len(self.points), "starved": self.starved}

"""What the devices measured over one bead: the source's current / voltage / wire feed, and the
robot's pace from its EXE reports (DESIGN.md §6: "done" and "deposited" come from the devices).

The travel speed is the slope of the lower envelope of the length reached against the arrival
time of each EXE, over the moves executed with the arc stable. An EXE can only arrive late, never
early (the robot's loop, the line and the host's reader all add delay), so the line that bounds
the points from below is the robot's pace and the points above it are delays; a least-squares
slope through all of them was pulled by any stretch of late arrivals (a host stall mid-bead:
up to 12 % off on the demo at time scale 120, where a 1 ms delay is 0.12 s of process time).
The envelope's edge over the middle of the bead is the optimum of the one-sided fit (minimise
the summed delays, all delays >= 0). An EXE is cumulative: the moves it covers share one arrival
time, and only the farthest of them is known to have just finished.
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
        if self.points and t == self.points[-1][0]:   # the same (cumulative) EXE: its farthest move
            self.points[-1] = (t, max(s, self.points[-1][1]))
            return
        self.points.append((t, s))

    def speed_mm_s(self) -> float | None:
        """Wall mm/s: the slope over the EXEs (two or more), else from the release to the one EXE."""
        pts = self.points
        if len(pts) >= 2:
            v = envelope_speed(pts)
            if v is not None:
                return v
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


def envelope_speed(points: list[tuple[float, float]]) -> float | None:
    """Slope ds/dt of the lower envelope of (arrival time, length) points, taken over the mean
    length: the pace that minimises the summed (one-sided) delays. None when it is undefined."""
    pts = sorted((s, t) for t, s in points)          # by length; t as a function of s
    hull: list[tuple[float, float]] = []
    for p in pts:
        while len(hull) >= 2:
            (s1, t1), (s2, t2) = hull[-2], hull[-1]
            if (t2 - t1) * (p[0] - s1) >= (p[1] - t1) * (s2 - s1):   # hull[-1] lies on or above
                hull.pop()
            else:
                break
        hull.append(p)
    s_mean = sum(s for s, _ in pts) / len(pts)
    for (s1, t1), (s2, t2) in zip(hull, hull[1:]):
        if s1 <= s_mean <= s2 and s2 > s1 and t2 > t1:
            return (s2 - s1) / (t2 - t1)
    return None

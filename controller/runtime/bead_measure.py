"""What the devices measured over one bead: the source's current / voltage / wire feed, and the
robot's pace from its EXE reports (docs/contract.md §6: "done" and "deposited" come from the devices).

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
from typing import Callable

import numpy as np

from controller.ports import MotionExecutor

BUS_CYCLE_S = 0.010   # the power source's bus cycle (wall): how finely the controller sees the process
# wall: how late a device's report may come without the torch having stood; the arc time forgives
# that much at the bead's start and end (docs/contract.md §6a: the simulators answer within 5 ms, p99)
REPORT_LATENCY_S = 0.005
_PLANNED = -1.0      # Pace._wall_speed: "at the plan's own pace" (per move where the plan has per-move speeds)


@dataclass
class BeadStats:
    """Current / voltage / WFS seen while the arc burned on one bead (every bus cycle: the
    record gives each signal's mean, min/max and its 5th/95th percentiles per bead)."""

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
    values: list[tuple[float, float, float]] = field(default_factory=list)

    def add(self, i: float, u: float, w: float) -> None:
        self.values.append((i, u, w))
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
                "wfs_mean": self.w_sum / self.n, "wfs_min": self.w_min, "wfs_max": self.w_max,
                **self.spread()}

    def spread(self) -> dict[str, float]:
        """The 5th and 95th percentiles of current, voltage and wire feed over the bead."""
        out: dict[str, float] = {}
        for k, name in enumerate(("i", "u", "wfs")):
            vals = sorted(v[k] for v in self.values)
            if vals:
                out[f"{name}_p5"] = percentile(vals, 5.0)
                out[f"{name}_p95"] = percentile(vals, 95.0)
        return out


def percentile(sorted_vals: list[float], q: float) -> float:
    """The q-th percentile of sorted values (linear between the two nearest ranks)."""
    if len(sorted_vals) == 1:
        return sorted_vals[0]
    x = (len(sorted_vals) - 1) * q / 100.0
    lo = int(math.floor(x))
    hi = min(lo + 1, len(sorted_vals) - 1)
    return sorted_vals[lo] + (sorted_vals[hi] - sorted_vals[lo]) * (x - lo)


@dataclass
class Pace:
    """EXE arrivals of one bead: (wall time, length reached along the pass in mm)."""

    t_release: float                      # wall time motion was released (the robot's !GO)
    s_release: float                      # length along the pass where the bead started, mm
    points: list[tuple[float, float]] = field(default_factory=list)
    starved: int = 0                      # times the robot's queue ran empty inside the bead
    t_arc_lost: float | None = None       # wall time the source first reported the arc not stable
    planned_mm_min: float | None = None   # the pass's planned travel speed (process mm/min)
    speed_tol: float = 0.10               # the material's tolerance.speed_pct as a fraction
    t_go: float | None = None             # when a device that sets off at once was sent its first move (CNC)
    # per-move planned speeds (cell-job/2): mm along the weld points and the process s to reach them
    plan_s: list[float] | None = None
    plan_t: list[float] | None = None
    # M4 (docs/laser-power.md): the S the device scales its process power from with its actual
    # speed; then its status reports (wall t, mm along, feed, power) judge a slow-down's energy
    power_s: float | None = None
    power: list[tuple[float, float, float, float]] = field(default_factory=list)
    # the plan's arrays, made once (np.interp on the lists converted them at every call: the
    # bead's figures took 10.7 ms of CPU on the device loop for 128 EXEs), and the last speed
    _plan_np: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)
    _speed_memo: tuple[object, float | None] | None = field(default=None, init=False, repr=False, compare=False)

    def _plan_arrays(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self.plan_s is None or self.plan_t is None or len(self.plan_s) < 2:
            return None
        if self._plan_np is None:
            self._plan_np = (np.asarray(self.plan_s, dtype=float), np.asarray(self.plan_t, dtype=float))
        return self._plan_np

    def planned_walls(self, ss: list[float], time_scale: float) -> list[float]:
        """`planned_wall` of every length in `ss`, at once."""
        arr = self._plan_arrays()
        x = np.asarray(ss, dtype=float)
        if arr is None:
            v = (self.planned_mm_min or 0.0) / 60.0 * time_scale
            return [float(w) for w in x / v] if v > 0 else [0.0] * len(ss)
        ps, pt = arr
        s_end, t_end = ps[-1], pt[-1]
        v_last = (s_end - ps[-2]) / max(t_end - pt[-2], 1e-12)
        w = np.where(x <= s_end, np.interp(x, ps, pt), t_end + (x - s_end) / max(v_last, 1e-12))
        return [float(t) for t in w / time_scale]

    def planned_wall(self, s: float, time_scale: float) -> float:
        """Wall seconds the plan takes from the pass's first point to `s` mm along it (each move at
        its own speed when the pass has per-move speeds, else at `planned_mm_min`)."""
        arr = self._plan_arrays()
        if arr is not None and self.plan_s is not None and self.plan_t is not None:
            s_end, t_end = self.plan_s[-1], self.plan_t[-1]
            if s <= s_end:
                return float(np.interp(s, arr[0], arr[1])) / time_scale
            v_last = (s_end - self.plan_s[-2]) / max(t_end - self.plan_t[-2], 1e-12)
            return (t_end + (s - s_end) / max(v_last, 1e-12)) / time_scale
        v = (self.planned_mm_min or 0.0) / 60.0 * time_scale
        return s / v if v > 0 else 0.0

    def arc_lost(self, t: float) -> None:
        """The source's arc-stable bit fell at wall time `t` (the first fall counts)."""
        if self.t_arc_lost is None:
            self.t_arc_lost = t

    def reached(self, t: float, s: float) -> None:
        if self.points and t == self.points[-1][0]:   # the same (cumulative) EXE: its farthest move
            self.points[-1] = (t, max(s, self.points[-1][1]))
            return
        self.points.append((t, s))

    def at(self, t: float, s: float) -> None:
        """A position report (a CNC status report): the torch s mm along the pass at wall time t.
        At the start it may not have set off yet: that says nothing of its pace."""
        if s > self.s_release + 1e-3:
            self.reached(t, s)

    def powered(self, t: float, s: float, feed: float, power: float) -> None:
        """A status report's feed and process power (mm/min, S) at wall time t, s mm along the pass."""
        self.power.append((t, s, feed, power))

    def _plan_mm_min(self, s: float) -> float | None:
        """The planned speed (process mm/min) of the move at `s` mm along the pass, or of the move
        after it where that is slower: grbl computes the power of the step segments it prepares,
        which run ahead of the position it reports, into the next block."""
        if self.plan_s is not None and self.plan_t is not None and len(self.plan_s) >= 2:
            k = min(max(int(np.searchsorted(self.plan_s, s, side="right")) - 1, 0), len(self.plan_s) - 2)
            v = [(self.plan_s[j + 1] - self.plan_s[j]) / (self.plan_t[j + 1] - self.plan_t[j]) * 60.0
                 for j in (k, k + 1) if j + 1 < len(self.plan_s) and self.plan_t[j + 1] > self.plan_t[j]]
            return min(v) if v else None
        return self.planned_mm_min

    def power_followed(self, t0: float, t1: float) -> bool:
        """With M4 in force: the device's reports in [t0, t1] all show its power at most its actual
        speed's share of S (S × feed / the planned speed, within the speed tolerance and one unit
        of the report's rounding): whatever slowed it put no more energy into a millimetre."""
        got = [p for p in self.power if t0 <= p[0] <= t1]
        if self.power_s is None or not got:
            return False
        for _, s, feed, power in got:
            v = self._plan_mm_min(s)
            if v is None or v <= 0 or power > self.power_s * feed / v * (1.0 + self.speed_tol) + 1.0:
                return False
        return True

    def speed_mm_s(self) -> float | None:
        """Wall mm/s: the slope over the EXEs (two or more), else from the release to the one EXE.
        With per-move planned speeds the slope is taken of the plan's time to each point instead of
        its length (how far ahead of or behind its own timing the device ran), as the one speed that
        would lay the bead in that time: its length over its planned time, times that pace."""
        key = (len(self.points), self.points[-1] if self.points else None, self.t_release, self.s_release)
        if self._speed_memo is not None and self._speed_memo[0] == key:
            return self._speed_memo[1]   # the bead's figures ask for it five times over the same reports
        v = self._speed()
        self._speed_memo = (key, v)
        return v

    def _speed(self) -> float | None:
        if self.plan_s is not None and self.plan_t is not None and len(self.plan_s) >= 2 and self.plan_t[-1] > 0:
            walls = self.planned_walls([s for _, s in self.points], 1.0)
            timed = [(t, w) for (t, _), w in zip(self.points, walls)]
            rate = self._slope(timed, (self.t_release, self.planned_wall(self.s_release, 1.0)))
            return None if rate is None else rate * self.plan_s[-1] / self.plan_t[-1]
        return self._slope(self.points, (self.t_release, self.s_release))

    def _slope(self, pts: list[tuple[float, float]], release: tuple[float, float]) -> float | None:
        """d(value)/dt over (wall time, value) reports: the lower envelope's, else end to end."""
        if len(pts) >= 2:
            v = envelope_speed(pts)
            if v is not None:
                return v
            t0, s0 = pts[0]
            t1, s1 = pts[-1]
            return (s1 - s0) / (t1 - t0) if t1 > t0 and s1 > s0 else None
        if len(pts) == 1:
            t1, s1 = pts[0]
            dt, ds = t1 - release[0], s1 - release[1]
            return ds / dt if dt > 0 and ds > 0 else None
        return None

    def figures(self, time_scale: float, length_mm: float) -> dict[str, float | int | None]:
        """Actual travel speed (process mm/min), the motion time that deposited `length_mm`
        (process s), the arc time (process s), the moves counted, the starvations and the
        torch's stand-stills with the arc on."""
        out: dict[str, float | int | None] = {"moves": len(self.points), "starved": self.starved,
                                              **self.arc_time(time_scale), **self.standstill(time_scale)}
        v = self.speed_mm_s()
        if v is None:
            return {"speed_mm_min": None, "motion_s": None, **out}
        v_process = v / time_scale                # wall mm/s -> process mm/s
        return {"speed_mm_min": v_process * 60.0, "motion_s": length_mm / v_process if length_mm > 0 else 0.0,
                **out}

    def motion_start(self, time_scale: float) -> float:
        """Wall time the torch started along the bead: the release, or later when the device
        took a while to start (a robot starts its first move some milliseconds after `!GO`).

        Each report bounds the start from above: the torch reached s_i by t_i, so at most at
        the pace v it left s_release at t_i - (s_i - s_release) / v or earlier; the earliest of
        those bounds is where it set off (the reports are late by about as much as the one that
        ends the bead, `motion_end`, so the two cancel). A device that sets off as soon as it has
        its first move (`t_go`: grbl starts a planned block at once) set off at t_go: a later
        start than that, beyond a report's latency (`REPORT_LATENCY_S`), is the torch standing
        still with the arc on before its first report, and in the arc time (a CNC starved by its
        host 10-55 ms, 0.6-3.3 s of process time at time scale 60)."""
        v = self._wall_speed(time_scale)
        if v is None or not self.points:
            return self.t_release
        if v == _PLANNED:   # at the plan's pace (per move where it has per-move speeds)
            w0 = self.planned_wall(self.s_release, time_scale)
            walls = self.planned_walls([s for _, s in self.points], time_scale)
            est = min(t - max(0.0, w - w0) for (t, _), w in zip(self.points, walls))
        else:
            est = min(t - max(0.0, s - self.s_release) / v for t, s in self.points)
        if self.t_go is not None:
            go = max(self.t_release, self.t_go)
            return go + min(max(0.0, est - go), REPORT_LATENCY_S)
        return max(self.t_release, est)

    def set_off(self, t_go: float) -> None:
        """The device sets off as soon as it has its first move, which it was sent at wall time t_go."""
        self.t_go = t_go

    def _wall_speed(self, time_scale: float, cycle_s: float = BUS_CYCLE_S) -> float | None:
        """The plan's pace (`_PLANNED`: per move where the plan has per-move speeds), or the measured
        one (wall mm/s) where the device clearly ran faster than its plan:
        by more than the speed tolerance and the two bus cycles each report may be late by, over
        the span of the reports. A stand-still mid-bead lowers the measured pace, which would push
        the start estimate early; two reports a few milliseconds late apart raise it (a CNC's two
        status reports over a bead at time scale 60: +13 %), which would push it late."""
        v_plan = self.planned_mm_min / 60.0 * time_scale if self.planned_mm_min else None
        v = self.speed_mm_s()
        span = max(t for t, _ in self.points) - min(t for t, _ in self.points) if self.points else 0.0
        if v_plan is None or (v is not None and span > 0
                              and v > v_plan * (1.0 + self.speed_tol + 2 * cycle_s / span)):
            return v
        return _PLANNED

    def arc_time(self, time_scale: float) -> dict[str, float | None]:
        """The bead's arc time in process seconds: from the torch setting off along the bead
        (after the release, which waits for the source's arc-stable edge: `motion_start`) to the
        end of the last move executed with the arc stable (`motion_end`), cut at the source's
        falling arc-stable edge when the arc was lost before. Ignition and the wait for the motion
        before the first move, and the crater after the last, are not in it."""
        if not self.points:
            return {"arc_s": 0.0 if self.t_arc_lost is not None else None}
        t_end = self.motion_end(time_scale)
        if self.t_arc_lost is not None:
            t_end = min(t_end, self.t_arc_lost)
        return {"arc_s": max(0.0, t_end - self.motion_start(time_scale)) * time_scale}

    def motion_end(self, time_scale: float) -> float:
        """Wall time the last move ended: its report, less the delay it came with beyond the
        report before it (at most a report's latency, `REPORT_LATENCY_S`). The last report is the
        only one that times the end; the start is timed by the earliest of them (`motion_start`),
        so a closing report later than the others would count its lateness as arc time."""
        t_last = max(t for t, _ in self.points)
        st = self._stretches(time_scale, BUS_CYCLE_S)
        if st is None or (self.t_arc_lost is not None and self.t_arc_lost < t_last):
            return t_last   # the arc's falling edge ends it
        d = st[1]
        return t_last - min(max(0.0, d[-1] - d[-2]), REPORT_LATENCY_S)

    def _stretches(self, time_scale: float, cycle_s: float
                   ) -> tuple[list[tuple[float, float]], list[float], list[tuple[float, float]]] | None:
        """The reports from the set-off (arc lost: up to it), their delays t - s / v against the
        planned pace, and per stretch between two reports the rise of the suffix minimum of the
        delays and the rise allowed (`standstill`); None without a plan or reports."""
        if not self.planned_mm_min or not self.points:
            return None
        t0 = self.motion_start(time_scale)
        pts = [(t0, self.s_release)] + sorted(self.points)
        if self.t_arc_lost is not None:
            pts = [p for p in pts if p[0] <= self.t_arc_lost] or pts[:1]
        w = self.planned_walls([s for _, s in pts], time_scale)   # wall s at the planned pace
        d = [t - wk for (t, _), wk in zip(pts, w)]
        suffix = d[:]
        for k in range(len(d) - 2, -1, -1):
            suffix[k] = min(suffix[k], suffix[k + 1])
        # the reports opening and closing the stretch are each seen to within one bus cycle
        return pts, d, [(suffix[k + 1] - suffix[k], self.speed_tol * max(0.0, w[k + 1] - w[k]) + 2 * cycle_s)
                        for k in range(len(pts) - 1)]

    def standstill(self, time_scale: float, cycle_s: float = BUS_CYCLE_S) -> dict[str, float | int | None]:
        """The torch standing still with the arc on, from the device's own progress reports.

        Each report (an EXE, a CNC status position) says the torch had reached length s by wall
        time t; at the planned speed it needs (s' - s) / v between two reports. A report can only
        be late, never early, so the suffix minimum of the delays t - s / v is where the torch
        really was behind its pace: it rises only when the torch stood still (or crawled), and a
        late report that the next ones make up for leaves it flat. A rise between two reports
        larger than the speed tolerance of that stretch plus two bus cycles (`cycle_s` wall, the
        resolution at which the controller sees the process, once for the report opening the
        stretch and once for the one closing it) is a stand-still. Returned in
        process seconds: `still_n` stand-stills, `still_s` their total, `still_max_s` the longest;
        `lag_s` is how much longer the whole bead took than its length at the planned speed.
        With M4 in force a stretch whose reports show the power following the speed
        (`power_followed`) is a slow-down, not a stand-still: `slowed_n` counts them (None: no M4).
        """
        st = self._stretches(time_scale, cycle_s)
        if st is None:
            return {"still_n": None, "still_s": None, "still_max_s": None, "lag_s": None}
        pts, _, stretches = st
        slow = [(rise, pts[k][0], pts[k + 1][0]) for k, (rise, allowed) in enumerate(stretches) if rise > allowed]
        rises = [rise for rise, t0, t1 in slow if not self.power_followed(t0, t1)]
        t_end, s_end = pts[-1]
        lag = (t_end - pts[0][0]) - max(0.0, self.planned_wall(s_end, time_scale) - self.planned_wall(self.s_release, time_scale))
        return {"still_n": len(rises), "still_s": sum(rises) * time_scale,
                "slowed_n": None if self.power_s is None else len(slow) - len(rises),
                "still_max_s": max(rises, default=0.0) * time_scale, "lag_s": lag * time_scale}


def follow_pace(executor: MotionExecutor, pace: Callable[[], Pace | None]) -> None:
    """The device's position (and process power) reports into the current bead's pace, if any."""
    def at(t: float, s: float) -> None:
        p = pace()
        if p is not None:
            p.at(t, s)

    def powered(t: float, s: float, feed: float, power: float) -> None:
        p = pace()
        if p is not None:
            p.powered(t, s, feed, power)
    executor.on_position(at)
    executor.on_power(powered)


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

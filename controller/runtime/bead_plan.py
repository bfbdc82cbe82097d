"""A pass's process per weld move (cell-job/2, docs/along-the-path.md): what the runner streams,
feeds and judges a bead against.

A `cell-job/2` pass carries a travel speed and a wire feed per job segment; the runner cuts the
pass into weld moves of at most `max_step_mm` (controller/job/weld_path.py), and each move takes
the values of the segment it lies on. A `cell-job/1` pass gives every move its one speed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controller.job.weld_path import move_values, weld_points, weld_segments
from planner.job import Pass


@dataclass(frozen=True)
class MovePlan:
    """One pass's planned speed and wire feed per weld move (move k: weld point k to k + 1)."""

    speed: float                      # the pass's planned speed: its length-weighted mean, mm/min
    speeds: float | list[float]       # what the executor streams: one speed, or one per move
    wfs: list[float] | None           # the wire feed per move (None: the pass's one, `wfs_mean`)
    wfs_mean: float                   # the pass's planned wire feed (length-weighted mean), m/min
    plan_t: list[float] | None        # process s to reach each weld point at the planned speeds (per-move speeds)
    plan_s: list[float] | None        # mm along the weld points (per-move speeds)

    @property
    def slowest(self) -> float:
        return self.speed if isinstance(self.speeds, float) else min(self.speeds)

    def wfs_at(self, k: int) -> float:
        """The wire feed of weld move k (clamped to the pass)."""
        if self.wfs is None:
            return self.wfs_mean
        return self.wfs[min(max(k, 0), len(self.wfs) - 1)]

    def wfs_range(self) -> tuple[float, float]:
        """The lowest and highest planned wire feed of the pass."""
        if self.wfs is None:
            return self.wfs_mean, self.wfs_mean
        return min(self.wfs), max(self.wfs)

    def speed_range(self) -> tuple[float, float]:
        """The lowest and highest planned travel speed of the pass."""
        if isinstance(self.speeds, float):
            return self.speeds, self.speeds
        return min(self.speeds), max(self.speeds)


def move_plan(p: Pass, max_step_mm: float) -> MovePlan:
    """The pass's speed and wire feed per weld move (deterministic: the job and the step only)."""
    if not p.per_segment:
        return MovePlan(p.speed_mm_min, float(p.speed_mm_min), None, p.wfs_m_min, None, None)
    segs = weld_segments(p.points, max_step_mm)
    speeds = move_values(p.speeds(), segs)
    wfs = move_values(p.wire_feeds(), segs) if p.seg_wfs_m_min is not None else None
    pts = np.asarray(weld_points(p.points, max_step_mm))
    lens = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    plan_s = np.r_[0.0, np.cumsum(lens)]
    plan_t = np.r_[0.0, np.cumsum(lens / np.asarray(speeds) * 60.0)]
    return MovePlan(p.speed_mm_min, speeds, wfs, p.wfs_m_min, plan_t.tolist(), plan_s.tolist())

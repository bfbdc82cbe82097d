"""A pass's polyline cut into weld moves: the indices the journal records and a resume re-arcs at."""
from __future__ import annotations

import math
from typing import Sequence, cast

import numpy as np

Point = tuple[float, float, float]


def weld_points(points: Sequence[Sequence[float]] | np.ndarray, max_step_mm: float) -> list[Point]:
    """The pass's polyline subdivided into moves of at most `max_step_mm` (deterministic).

    Point indices of this list are what the journal records, so they must not change between
    a run and its resume: they depend on the job and the step only.
    """
    return _subdivide(points, max_step_mm)[0]


def weld_segments(points: Sequence[Sequence[float]] | np.ndarray, max_step_mm: float) -> list[int]:
    """For every weld move of `weld_points` (move k ends at weld point k + 1), the job segment it
    lies on (segment i runs from the pass's point i to i + 1): how a per-segment speed or wire
    feed (cell-job/2) reaches the moves."""
    return _subdivide(points, max_step_mm)[1]


def move_speed(speed: float | Sequence[float], k: int) -> float:
    """The travel speed of weld move k (from weld point k to k + 1): the bead's one speed, or its
    per-move list's k-th (clamped to the list)."""
    if isinstance(speed, (int, float)):
        return float(speed)
    return float(speed[min(max(k, 0), len(speed) - 1)])


def move_values(seg_values: np.ndarray, segments: Sequence[int]) -> list[float]:
    """The per-segment values (one per job segment) as one per weld move."""
    return [float(seg_values[i]) for i in segments]


def _subdivide(points: Sequence[Sequence[float]] | np.ndarray, max_step_mm: float) -> tuple[list[Point], list[int]]:
    if isinstance(points, np.ndarray):   # a typed pass's points: the same floats as the file's list
        points = points.tolist()
    # a job point is x y z (a longer one carries more: only the first three are the position)
    out: list[Point] = [cast(Point, tuple(float(v) for v in points[0][:3]))]
    seg: list[int] = []
    for j, p in enumerate(points[1:]):
        q = tuple(float(v) for v in p[:3])
        a = out[-1]
        d = math.dist(a, q)
        if d < 1e-9:
            continue
        n = max(1, math.ceil(d / max_step_mm - 1e-9))
        for k in range(1, n + 1):
            f = k / n
            out.append((a[0] + (q[0] - a[0]) * f, a[1] + (q[1] - a[1]) * f, a[2] + (q[2] - a[2]) * f))
            seg.append(j)
    return out, seg

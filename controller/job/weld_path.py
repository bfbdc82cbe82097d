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
    if isinstance(points, np.ndarray):   # a typed pass's points: the same floats as the file's list
        points = points.tolist()
    # a job point is x y z (a longer one carries more: only the first three are the position)
    out: list[Point] = [cast(Point, tuple(float(v) for v in points[0][:3]))]
    for p in points[1:]:
        q = tuple(float(v) for v in p[:3])
        a = out[-1]
        d = math.dist(a, q)
        if d < 1e-9:
            continue
        n = max(1, math.ceil(d / max_step_mm - 1e-9))
        for k in range(1, n + 1):
            f = k / n
            out.append((a[0] + (q[0] - a[0]) * f, a[1] + (q[1] - a[1]) * f, a[2] + (q[2] - a[2]) * f))
    return out

"""The pour of one chunk of bead and its bookkeeping (sims/heightmap.py pours with these)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Generator, TypeVar

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass
class Laid:
    """What one segment's bead did: its rise on the centre line where the pool has passed
    (w/2 behind the segment's end; None that close to the bead's start), metal not placed."""

    rise_mm: float | None
    lost_mm3: float


T = TypeVar("T")


def finish(steps: Generator[None, None, T]) -> T:
    """Run a resumable pour (`HeightMap.lay_steps`) to its end; its value."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            value: T = done.value
            return value


def pour_level(old: FloatArray, env: FloatArray, need: float) -> float:
    """The level c at which Σ clip(c − old, 0, env − old) = need (cells' height sum); inf when full."""
    m = env > old
    o, e = old[m], env[m]
    if o.size == 0 or need >= float(np.sum(e - o)):
        return math.inf
    bp = np.concatenate([o, e])
    ds = np.concatenate([np.ones(o.size), -np.ones(e.size)])
    idx = np.argsort(bp, kind="stable")
    bp, ds = bp[idx], ds[idx]
    slope = np.cumsum(ds)
    val = np.concatenate([[0.0], np.cumsum(slope[:-1] * np.diff(bp))])
    k = int(np.searchsorted(val, need, side="right")) - 1
    k = min(max(k, 0), bp.size - 1)
    while k < bp.size - 1 and slope[k] <= 0:
        k += 1
    return float(bp[k] + (need - val[k]) / slope[k])


def frame(ii: NDArray[np.int64], jj: NDArray[np.int64], cell: float, a: FloatArray, u: FloatArray,
           nrm: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Cell centres in a segment's frame: along it from its start a, and across it."""
    cx, cy = (ii + 0.5) * cell - a[0], (jj + 0.5) * cell - a[1]
    return cx * u[0] + cy * u[1], cx * nrm[0] + cy * nrm[1]


@dataclass
class Chunk:
    """About 1 mm of a bead waiting in its pool: its cells (`round_end`: those of its segment's
    round end, beyond the segment's end), their distances to the segment, its centre cell, the
    pour's width, peak and metal (cell-heights), its segment's end point (None but for the
    bead's last chunk so far) and its place along the bead."""

    ii: NDArray[np.int64]
    jj: NDArray[np.int64]
    s: FloatArray
    round_end: NDArray[np.bool_]
    centre: tuple[int, int]
    width: float
    peak: float
    need: float
    at: FloatArray | None
    path_mm: float


def metal_per_cell(cell: float, a: FloatArray, u: FloatArray, nrm: FloatArray, length: float, half: float) -> float:
    """mm of bead one cell of a segment's strip stands for (segment from a, direction u, normal
    nrm, half width `half`): counted over the strip extended by a bead width beyond both ends, to
    whole cells (0 when the strip holds no cell). Counted over the segment alone, a 3.44 mm move
    covering 6 or 7 rows of 0.5 mm cells poured its metal 1/6 higher on 6: a step at every joint,
    the same every layer where the plan's points repeat."""
    ext = cell * math.ceil((length + 4.0 * half) / cell)   # whole cells: along a grid line it counts exactly
    a0 = a - u * 2 * half
    lo = np.minimum(a0, a0 + u * ext) - half
    hi = np.maximum(a0, a0 + u * ext) + half
    gi, gj = np.meshgrid(np.arange(math.floor(lo[0] / cell), math.floor(hi[0] / cell) + 1, dtype=np.int64),
                         np.arange(math.floor(lo[1] / cell), math.floor(hi[1] / cell) + 1, dtype=np.int64))
    t, s = frame(gi.ravel(), gj.ravel(), cell, a0, u, nrm)
    n = int(np.count_nonzero((t >= 0.0) & (t < ext) & (np.abs(s) <= half)))
    if n == 0 or not np.any((t >= 2 * half) & (t <= 2 * half + length) & (np.abs(s) <= half)):
        return 0.0
    return ext / n


def merge_cells(ii: NDArray[np.int64], jj: NDArray[np.int64], env: FloatArray,
                hang: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray, FloatArray]:
    """Cells listed more than once (a pool's chunks overlap) once each, with the highest of their
    parabolas and hangs."""
    key = (jj - jj.min()) * (int(ii.max() - ii.min()) + 1) + (ii - ii.min())
    uniq, inv = np.unique(key, return_inverse=True)
    top, low = np.full(uniq.size, -np.inf), np.full(uniq.size, -np.inf)
    np.maximum.at(top, inv, env)
    np.maximum.at(low, inv, hang)
    first = np.zeros(uniq.size, dtype=np.int64)
    first[inv[::-1]] = np.arange(inv.size)[::-1]
    return ii[first], jj[first], top, low


def alone_rise(c: Chunk, old: FloatArray, base: float, off_part: float) -> float:
    """The rise on a chunk's centre line were it poured alone on the surface `old` of its cells,
    resting on `base` (its centre's surface before the bead)."""
    env = base + c.peak * (1.0 - (2.0 * c.s / c.width) ** 2)
    floor = np.where(old < off_part, base - c.peak, old)
    level = pour_level(floor, env, c.need)
    k = int(np.argmin(c.s))
    return float(max(floor[k], min(level, env[k])) - base)

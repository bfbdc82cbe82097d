"""The path loop, the pure half (docs/closed-loop.md "Along the path"): heights along a pass from
samples binned by position, fields indexed by position in the part, and the learning law that
turns the last layer's height error into the next layer's per-segment speed factors.

No I/O, no clocks: numpy arrays and frozen dataclasses, unit-tested on their own.

The law (PD-type iterative learning control over layers, indexed by xy in the part, not by point
number, so alternating or re-planned passes line up): after layer i, with d_i(x) its measured top
minus the layer's mean top (the layer loop holds the mean), the speed factor of the next layer's
segment at x is

    m_{i+1}(x) = m_i(x) + (kp·(d_i(x) − d_{i−1}(x)) + ki·d_i(x)) / r

r the layer's rise: a bead's rise follows its metal, 1/speed, so a factor change Δm changes the
rise by about −r·Δm. d, m are fields: kernel means (Gaussian, σ a quarter of the filter length, so its ±2σ span
it) of the samples near x, the nearest within the filter length where none is that near; the
samples themselves are means over bins of about one bead width, so the correction is filtered
along the path over at least one bead width. The
factors are scaled so their length-weighted mean of 1/m is 1 (the layer's metal stays the layer
loop's), then bounded by the speed trim.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from planner.pour import BeadLaw

FloatArray = NDArray[np.float64]

__all__ = ["Field", "resample", "arc_length", "point_at", "bin_samples", "plan_factors", "PathLaw", "spots_along",
           "rise_ratio", "process_for", "spread_reports", "sides", "cut_polyline", "NO_CUTS"]

NO_CUTS: FloatArray = np.zeros((0, 4))


def sides(xy: FloatArray, cuts: FloatArray, reach: float) -> FloatArray:
    """(n, k): which side of every cut (a point and the path's unit direction there, x y ux uy) each
    point lies on, +1 ahead, -1 behind, 0 farther than `reach` from it (the cut does not part it)."""
    q = np.asarray(xy, dtype=float).reshape(-1, 2)
    c = np.asarray(cuts, dtype=float).reshape(-1, 4)
    rel = q[:, None, :] - c[None, :, :2]
    along = (rel * c[None, :, 2:]).sum(axis=2)
    near = np.hypot(rel[..., 0], rel[..., 1]) <= reach
    out: FloatArray = np.where(near, np.where(along >= 0.0, 1.0, -1.0), 0.0)
    return out


def parted(q: FloatArray, xy: FloatArray, cuts: FloatArray, reach: float) -> NDArray[np.bool_]:
    """(n, m): query n and sample m lie on opposite sides of a cut (a hidden region's edge)."""
    if not len(cuts):
        return np.zeros((len(q), len(xy)), dtype=bool)
    a, b = sides(q, cuts, reach), sides(xy, cuts, reach)
    out: NDArray[np.bool_] = np.any(a[:, None, :] * b[None, :, :] < 0.0, axis=2)
    return out


def cut_polyline(points: FloatArray, idx: FloatArray, cuts: FloatArray, min_mm: float = 0.05) -> tuple[FloatArray, FloatArray]:
    """The polyline with a point inserted where it crosses every cut (within a bead width of the
    cut's point), so a segment never straddles a region's edge; idx (fractional indices into the
    original points) carried over."""
    pts, ix = np.asarray(points, dtype=float), np.asarray(idx, dtype=float)
    for x, y, ux, uy in np.asarray(cuts, dtype=float).reshape(-1, 4):
        a = (pts[:, 0] - x) * ux + (pts[:, 1] - y) * uy
        for k in range(len(pts) - 1):
            if (a[k] < 0.0) != (a[k + 1] < 0.0) and abs(a[k] - a[k + 1]) > 1e-12:
                f = a[k] / (a[k] - a[k + 1])
                q = pts[k] + f * (pts[k + 1] - pts[k])
                seg = float(np.hypot(*(pts[k + 1, :2] - pts[k, :2])))
                if np.hypot(q[0] - x, q[1] - y) > 7.0 or min(f, 1.0 - f) * seg < min_mm:
                    continue
                pts = np.insert(pts, k + 1, q, axis=0)
                ix = np.insert(ix, k + 1, ix[k] + f * (ix[k + 1] - ix[k]))
                break
    return pts, ix



@dataclass(frozen=True)
class Field:
    """A quantity sampled at positions of the part (substrate xy, mm)."""

    xy: FloatArray     # (n, 2)
    v: FloatArray      # (n,)

    @staticmethod
    def of(rows: Sequence[Sequence[float]]) -> "Field":
        a = np.asarray(rows, dtype=float).reshape(-1, 3)
        return Field(a[:, :2].copy(), a[:, 2].copy())

    def rows(self, nd: int = 4) -> list[list[float]]:
        return [[round(float(x), 3), round(float(y), 3), round(float(v), nd)] for (x, y), v in zip(self.xy, self.v)]

    def at(self, q: FloatArray, sigma: float, reach: float | None = None, cuts: FloatArray = NO_CUTS) -> FloatArray:
        """Kernel mean at each query point (n, 2) over the samples within 2σ; where there is none,
        the nearest sample within `reach` (else NaN). A sample across one of the `cuts` (a
        region's edge) from the query is not used."""
        q = np.asarray(q, dtype=float).reshape(-1, 2)
        out = np.full(len(q), np.nan)
        if not len(self.v) or not len(q):
            return out
        d2 = ((q[:, None, :] - self.xy[None, :, :]) ** 2).sum(axis=2)
        if len(cuts):
            d2 = np.where(parted(q, self.xy, cuts, max(2.0 * sigma, reach or 0.0)), np.inf, d2)
        w = np.exp(-0.5 * d2 / (sigma * sigma))
        w[d2 > (2.0 * sigma) ** 2] = 0.0
        s = w.sum(axis=1)
        ok = s > 1e-9
        out[ok] = (w[ok] @ self.v) / s[ok]
        near = np.argmin(d2, axis=1)
        fill = ~ok & (d2[np.arange(len(q)), near] <= (reach if reach is not None else 2.0 * sigma) ** 2)
        out[fill] = self.v[near[fill]]
        return out


def arc_length(points: FloatArray) -> FloatArray:
    """Cumulative xy length at every point (0 at the first)."""
    p = np.asarray(points, dtype=float)
    if len(p) < 2:
        return np.zeros(len(p))
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p[:, :2], axis=0).T))])


def point_at(points: FloatArray, cum: FloatArray, s: float) -> FloatArray:
    """The point (all columns) at length s along the polyline."""
    s = min(max(s, 0.0), float(cum[-1]))
    k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(cum) - 2)
    seg = cum[k + 1] - cum[k]
    t = 0.0 if seg <= 0 else (s - cum[k]) / seg
    out: FloatArray = points[k] + t * (points[k + 1] - points[k])
    return out


def resample(points: FloatArray, spacing: float) -> tuple[FloatArray, FloatArray]:
    """The polyline with points inserted so that no segment is longer than `spacing` (every
    original point kept); also each new point's fractional index into the original points (for
    interpolating per-point arrays: normals, axes)."""
    p = np.asarray(points, dtype=float)
    out, idx = [p[0]], [0.0]
    for i in range(len(p) - 1):
        n = max(1, math.ceil(float(np.hypot(*(p[i + 1, :2] - p[i, :2]))) / spacing - 1e-9))
        for k in range(1, n + 1):
            f = k / n
            out.append(p[i] + f * (p[i + 1] - p[i]))
            idx.append(i + f)
    return np.asarray(out), np.asarray(idx)


def bin_samples(samples: Sequence[tuple[float, float]], length: float, bin_mm: float,
                min_n: int = 1, breaks: Sequence[float] = ()) -> list[tuple[float, float, int]]:
    """Samples (s along the pass, value) binned by position: (the samples' mean s, mean value, n)
    for every bin of about `bin_mm` (the pass split into equal bins, and at every s in `breaks`,
    a region's edge) holding at least `min_n`."""
    if length <= 0 or not samples:
        return []
    nb = max(1, int(round(length / bin_mm)))
    size = length / nb
    acc: dict[tuple[int, int], list[tuple[float, float]]] = {}
    for s, v in samples:
        if math.isfinite(v):
            acc.setdefault((min(max(int(s / size), 0), nb - 1), sum(1 for b in breaks if s >= b)), []).append((s, v))
    return [(float(np.mean([a for a, _ in sv])), float(np.mean([b for _, b in sv])), len(sv))
            for _, sv in sorted(acc.items()) if len(sv) >= min_n]


def spread_reports(samples: Sequence[tuple[float, float]], end_mm: float) -> list[tuple[float, float]]:
    """Samples tagged with the last point the device reported reaching, placed where the torch was:
    the torch is past that point, on the move to the next one reported, and the source samples at a
    steady rate, so the samples of one report spread evenly over the stretch to the next report's
    point (the last one's to the pass's end). Undoes the lag of up to a move, which changes sign
    with the pass's direction (a wall laid back and forth)."""
    out: list[tuple[float, float]] = []
    i, n = 0, len(samples)
    while i < n:
        j = i
        while j < n and samples[j][0] == samples[i][0]:
            j += 1
        s0 = samples[i][0]
        s1 = samples[j][0] if j < n else max(end_mm, s0)
        s1 = max(s1, s0)
        out += [(s0 + (s1 - s0) * (k + 0.5) / (j - i), samples[k + i][1]) for k in range(j - i)]
        i = j
    return out


def spots_along(points: FloatArray, spacing: float, end_mm: float) -> list[FloatArray]:
    """Probe spots along a pass: every ~`spacing` mm from `end_mm` after its start to `end_mm`
    before its end (ends included), at least one (its middle)."""
    p = np.asarray(points, dtype=float)
    cum = arc_length(p)
    total = float(cum[-1]) if len(cum) else 0.0
    if total <= 2 * end_mm:
        return [point_at(p, cum, total / 2)] if total > 0 else []
    n = max(1, int(round((total - 2 * end_mm) / spacing)))
    return [point_at(p, cum, end_mm + (total - 2 * end_mm) * k / n) for k in range(n + 1)]


@dataclass(frozen=True)
class PathLaw:
    kp: float = 0.4            # on the change of the error since the last layer (damping)
    ki: float = 0.2            # on the error (learning)
    filter_mm: float = 10.5    # the kernel spans it: σ = filter_mm / 4
    bounds: tuple[float, float] = (0.75, 1.25)
    elasticity: float = 1.0    # p: the rise follows m^-p (a wall: 1 + Ribeiro's K3, the bead widening as it slows)
    max_step: float = 0.15     # the factor changes by at most this from one layer to the next


def bounded_metal(m: FloatArray, w: FloatArray, lo: float, hi: float, rounds: int = 6) -> FloatArray:
    """The factors scaled so their length-weighted mean of 1/m is 1 (the layer's metal unchanged)
    after the bound: the stretches at a bound keep it and the others take up the difference, so one
    stretch far out (a wall's end) does not push every other one to the bound."""
    out = np.clip(m, lo, hi)
    if w.sum() <= 0:
        return out
    for _ in range(rounds):
        free = (out > lo + 1e-9) & (out < hi - 1e-9)
        need = float(w.sum() - np.sum(w[~free] / out[~free]))     # Σ w/m the free ones must make
        have = float(np.sum(w[free] / out[free]))
        if not free.any() or have <= 0 or need <= 0:
            break
        out = np.where(free, np.clip(out * have / need, lo, hi), out)
    return out


def plan_factors(mid_xy: FloatArray, seg_len: FloatArray, d_now: Field, d_prev: Field | None,
                 m_now: Field | None, rise_mm: float, law: PathLaw, cuts: FloatArray = NO_CUTS) -> tuple[FloatArray, FloatArray]:
    """The next layer's speed factor per segment (midpoints `mid_xy`, lengths `seg_len`, all the
    layer's passes together): (bounded factors, needed factors before the bound)."""
    sigma, reach = law.filter_mm / 4.0, law.filter_mm
    dn = d_now.at(mid_xy, sigma, reach, cuts)
    dp = d_prev.at(mid_xy, sigma, reach, cuts) if d_prev is not None else np.full(len(dn), np.nan)
    mn = m_now.at(mid_xy, sigma, reach, cuts) if m_now is not None else np.full(len(dn), np.nan)
    mn = np.where(np.isfinite(mn), mn, 1.0)
    dp = np.where(np.isfinite(dp), dp, 0.0)       # first measured layer: the one under it level
    step = np.where(np.isfinite(dn), law.kp * (dn - dp) + law.ki * dn, 0.0) / (max(rise_mm, 1e-3) * law.elasticity)
    w = np.asarray(seg_len, dtype=float)
    want = np.maximum(mn + step, 0.05)
    need = want * float(np.sum(w / want) / np.sum(w)) if w.sum() > 0 else want
    m = np.maximum(mn + np.clip(step, -law.max_step, law.max_step), 0.05)   # one layer's reading moves it this far at most
    lo, hi = law.bounds
    return bounded_metal(m, w, lo, hi), need


def rise_ratio(law: BeadLaw, v: FloatArray, f: FloatArray, v0: FloatArray, f0: FloatArray) -> FloatArray:
    """A bead's rise at (speed v, wire feed f) over its rise at (v0, f0): metal over width,
    (f/v) / w(I(f), v), the synergic current I and Ribeiro's width w."""
    out: FloatArray = (f / v) / law.width(f, v) / ((f0 / v0) / law.width(f0, v0))
    return out


def process_for(rise: FloatArray, v0: FloatArray, f0: FloatArray, law: BeadLaw,
                speed: tuple[FloatArray, FloatArray], wfs: tuple[FloatArray, FloatArray]) -> tuple[FloatArray, FloatArray]:
    """(speed, wire feed) per segment that lay `rise` × the rise of (v0, f0) keeping the bead's width
    (docs/closed-loop.md "The wire feed"): more metal is a slower bead at a lower wire feed, less a
    faster one at a higher, so the rise follows the metal and the bead never runs wider than the
    layer under it (a wider bead pours its metal down a wall's sides). Where the wire feed reaches
    its bound (`wfs` lo, hi per segment) the speed alone takes the rest (the width gives); then the
    speed's bound (`speed` lo, hi)."""
    rise = np.asarray(rise, dtype=float)
    keep = law.width(f0, v0)
    lo, hi = wfs[0].astype(float).copy(), wfs[1].astype(float).copy()
    for _ in range(30):   # along f/v = rise·f0/v0 the width rises with f
        mid = 0.5 * (lo + hi)
        wide = law.width(mid, mid * v0 / (rise * f0)) > keep
        hi, lo = np.where(wide, mid, hi), np.where(wide, lo, mid)
    f = np.clip(0.5 * (lo + hi), wfs[0], wfs[1])
    # the speed that lays the rise at this feed: rise ∝ f·I(f)^-k2·v^(-1-k3)
    base = rise_ratio(law, v0, f, v0, f0)
    v = v0 * (base / np.maximum(rise, 1e-6)) ** (1.0 / (1.0 + law.k3))
    return np.clip(v, speed[0], speed[1]), f

"""The hidden regions' edges along a pass (docs/closed-loop.md "Region edges"): where the metal a
segment lays steps, a segment straddling the step lays one process over both sides and grows a pit
and a ridge the binned loop never sees. Found by a change-point fit on the raw stick-out samples
(finer than the bins) of the last layers, as the rise each sample saw times the factor it was laid
with: that is the world's gain there, whatever the loop did about it. No I/O, no clocks.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from controller.runtime.path_plan import NO_CUTS, FloatArray, Field, point_at

__all__ = ["EdgeFinder", "best_steps"]


def best_steps(s: FloatArray, g: FloatArray, lo: float, hi: float, half: float, min_t: float, min_step: float,
               grid_mm: float = 0.1) -> list[tuple[float, float, float]]:
    """Steps of g(s) with their edge in [lo, hi]: at every c on a `grid_mm` grid, a level each side
    over ±`half`; (edge, step, t) of the local best fits whose step is at least `min_step` and `min_t`
    standard errors, at least `half` apart."""
    order = np.argsort(s)
    s, g = s[order], g[order]
    c1, c2 = np.concatenate([[0.0], np.cumsum(g)]), np.concatenate([[0.0], np.cumsum(g * g)])
    cand: list[tuple[float, float, float]] = []
    for c in np.arange(lo, hi + 1e-9, grid_mm):
        a, m, b = (int(np.searchsorted(s, x)) for x in (c - half, c, c + half))
        nl, nr = m - a, b - m
        if nl < 4 or nr < 4:
            continue
        ml, mr = (c1[m] - c1[a]) / nl, (c1[b] - c1[m]) / nr
        sse = (c2[m] - c2[a]) - nl * ml * ml + (c2[b] - c2[m]) - nr * mr * mr
        sig = float(np.sqrt(max(sse / (nl + nr - 2), 1e-12) * (1.0 / nl + 1.0 / nr)))
        t = abs(mr - ml) / sig
        if t >= min_t and abs(mr - ml) >= min_step:
            # the edge lies between the samples either side of c: their middle
            cand.append((t, 0.5 * (float(s[m - 1]) + float(s[m])), float(mr - ml)))
    out: list[tuple[float, float, float]] = []
    for t, c, st in sorted(cand, reverse=True):
        if all(abs(c - o) >= half for o, _, _ in out):
            out.append((c, st, t))
    return out


def factor_at(laid: list[tuple[FloatArray, FloatArray]], xy: FloatArray) -> FloatArray:
    """The factor of the segment nearest each point (1 where no pass was laid)."""
    out = np.ones(len(xy))
    best = np.full(len(xy), np.inf)
    for pts, fac in laid:
        if len(fac) != len(pts) - 1:
            continue
        a, b = pts[:-1, :2], pts[1:, :2]
        d = b - a
        n2 = np.maximum((d * d).sum(axis=1), 1e-12)
        t = np.clip(((xy[:, None, :] - a[None]) * d[None]).sum(axis=2) / n2[None], 0.0, 1.0)
        dist = np.hypot(*(xy[:, None, :] - (a[None] + t[..., None] * d[None])).transpose(2, 0, 1))
        k = np.argmin(dist, axis=1)
        dk = dist[np.arange(len(xy)), k]
        better = dk < best
        out[better], best[better] = fac[k[better]], dk[better]
    return out


def straights(points: FloatArray, cos_tol: float = 0.9995) -> list[tuple[FloatArray, FloatArray]]:
    """The polyline's straight stretches (start, end xy): runs of segments going the same way."""
    p = np.asarray(points, dtype=float)[:, :2]
    out: list[tuple[FloatArray, FloatArray]] = []
    start, u0 = 0, None
    for k in range(len(p) - 1):
        d = p[k + 1] - p[k]
        n = float(np.hypot(*d))
        if n < 1e-9:
            continue
        u = d / n
        if u0 is not None and float(u @ u0) < cos_tol:
            out.append((p[start], p[k]))
            start = k
        u0 = u if u0 is None or float(u @ u0) < cos_tol else u0
    if len(p) > 1:
        out.append((p[start], p[-1]))
    return out


@dataclass
class EdgeFinder:
    """The last layers' raw samples along every pass and the edges (cuts: x y ux uy) found in them."""

    width_mm: float
    keep_layers: int = 8
    min_t: float = 4.5              # a new edge: a step this many standard errors, two layers running
    keep_t: float = 2.0             # a known edge: kept while its step stays this many
    min_step: float = 0.3           # the gain's relative step
    near_mm: float = 1.0            # a new edge: the same from one layer to the next
    drop_after: int = 3             # a known edge not seen again (within a bead width) this many layers running: dropped
    _miss: list[int] = field(default_factory=list)   # per cut: the layers running it was not seen
    _seen: FloatArray = field(default_factory=lambda: NO_CUTS)   # last layer's candidates not yet taken
    cuts: FloatArray = field(default_factory=lambda: NO_CUTS)
    _tops: dict[int, list[tuple[FloatArray, FloatArray]]] = field(default_factory=dict)   # layer: [(xy, top)]
    _laid: dict[int, list[tuple[FloatArray, FloatArray]]] = field(default_factory=dict)   # layer: [(points, factors)]
    _gains: dict[int, list[tuple[FloatArray, FloatArray, FloatArray]]] = field(default_factory=dict)  # layer: [(pts, xy, g)]

    def add(self, la: int, pa: int, points: FloatArray, cum: FloatArray, samples: list[tuple[float, float]],
            factors: FloatArray) -> None:
        """A pass's raw tops (s, top) and the metal factor of every segment it was laid with. Its
        samples' gain: the height the last layers laid there (this top less the top `keep_layers`
        back: the layers between cancel, so their noise does not add up) over the metal they were
        laid with there (Σ 1/m), relative to the pass's median."""
        pts = np.asarray(points, dtype=float)
        self._laid.setdefault(la, []).append((pts, np.asarray(factors, dtype=float)))
        if len(samples) < 8:
            return
        s = np.asarray([a for a, _ in samples], dtype=float)
        top = np.asarray([b for _, b in samples], dtype=float)
        xy = np.asarray([point_at(pts, cum, float(v))[:2] for v in s], dtype=float)
        self._tops.setdefault(la, []).append((xy, top))
        back = min(self.keep_layers, la)
        below = self._tops.get(la - back)
        if not below or back < 2:
            return
        prev = Field(np.concatenate([b[0] for b in below]), np.concatenate([b[1] for b in below]))
        under = prev.at(xy, 1.0, 2.0)
        metal = np.zeros(len(xy))
        for k in range(la - back + 1, la + 1):
            metal += 1.0 / np.maximum(factor_at(self._laid.get(k, []), xy), 1e-3)
        g = (top - under) / metal
        ok = np.isfinite(g)
        if ok.sum() < 8:
            return
        g = g[ok] / max(float(np.median(g[ok])), 1e-6)
        self._gains[la] = [(pts, xy[ok], g)] + [x for x in self._gains.get(la, []) if x[0] is not pts]

    def find(self, la: int) -> FloatArray:
        """After layer la: the edges along its passes over the last layers' gains (each pass's ends
        left out: a bead's run-in and end are no region's edge); the cuts the next layer is laid with."""
        self._prune(la)
        if la not in self._gains:
            return self.cuts
        all_xy = np.concatenate([g[1] for k in self._gains for g in self._gains[k]])
        all_g = np.concatenate([g[2] for k in self._gains for g in self._gains[k]])
        cuts: list[list[float]] = []
        seen: list[list[float]] = []
        for pts, _xy, _g in self._gains[la]:
            for a, b in straights(pts):   # each straight stretch of the pass on its own
                for q, u, t in self._steps_along(a, b, all_xy, all_g):
                    row = [float(q[0]), float(q[1]), float(u[0]), float(u[1])]
                    if self._close(q, self.cuts, self.width_mm) or (t >= self.min_t and self._close(q, self._seen, self.near_mm)):
                        cuts.append(row)
                    elif t >= self.min_t:
                        seen.append(row)
        # a region does not move: an edge found stays (where it was last seen) a few layers unseen
        new = np.asarray(cuts, dtype=float).reshape(-1, 4)
        kept = [(list(c), m + 1) for c, m in zip(self.cuts, self._miss) if not self._close(c[:2], new, self.width_mm)]
        kept = [(c, m) for c, m in kept if m < self.drop_after]
        self.cuts = np.asarray(cuts + [c for c, _ in kept], dtype=float).reshape(-1, 4)
        self._miss = [0] * len(cuts) + [m for _, m in kept]
        self._seen = np.asarray(seen, dtype=float).reshape(-1, 4)
        return self.cuts

    def _prune(self, la: int) -> None:
        """Forget what no later layer needs: tops and factors `keep_layers` back, gains but the last two."""
        for old in [k for k in self._tops if k < la - self.keep_layers]:
            self._tops.pop(old, None)
            self._laid.pop(old, None)
        for old in [k for k in self._gains if k < la - 1]:
            self._gains.pop(old, None)

    def _steps_along(self, a: FloatArray, b: FloatArray, xy: FloatArray, g: FloatArray) -> list[tuple[FloatArray, FloatArray, float]]:
        """(point, direction, t) of the gain's steps along the straight a→b (its samples within half
        a bead width of it; a bead width and a half at either end left out)."""
        ln = float(np.hypot(*(b - a)))
        if ln < 4.0 * self.width_mm:
            return []
        u = (b - a) / ln
        rel = xy - a
        along = rel @ u
        near = (np.abs(rel @ np.array([-u[1], u[0]])) <= self.width_mm / 2.0) & (along >= 0.0) & (along <= ln)
        return [(a + u * c, u, t) for c, _st, t in best_steps(along[near], g[near], 1.5 * self.width_mm, ln - 1.5 * self.width_mm,
                                                             self.width_mm, self.keep_t, self.min_step)]

    def forget_misses(self) -> None:
        """The cuts set from the journal (a resume): none missed yet."""
        self._miss = [0] * len(self.cuts)

    @staticmethod
    def _close(q: FloatArray, cuts: FloatArray, within: float) -> bool:
        return bool(len(cuts)) and float(np.hypot(cuts[:, 0] - q[0], cuts[:, 1] - q[1]).min()) <= within

    @staticmethod
    def breaks(points: FloatArray, cum: FloatArray, cuts: FloatArray) -> list[float]:
        """Where along the pass (s, mm) it crosses a cut: a bin never straddles a region's edge."""
        out = []
        for x, y, ux, uy in np.asarray(cuts, dtype=float).reshape(-1, 4):
            a = (points[:, 0] - x) * ux + (points[:, 1] - y) * uy
            for k in range(len(points) - 1):
                if (a[k] < 0.0) != (a[k + 1] < 0.0) and abs(a[k] - a[k + 1]) > 1e-12:
                    q = points[k, :2] + a[k] / (a[k] - a[k + 1]) * (points[k + 1, :2] - points[k, :2])
                    if np.hypot(q[0] - x, q[1] - y) <= 7.0:
                        out.append(float(cum[k] + np.hypot(*(q - points[k, :2]))))
        return sorted(out)

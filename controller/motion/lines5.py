"""The machine lines of a 5-axis pass: as few and as long as the tolerance allows (docs/kinematics.md "Lines").

Pure: numpy in, a `Lines` out. The machine interpolates every axis linearly between two line
ends, so on a turning table the tool tip leaves the straight planned path between them. A line
runs from one planned point as far along the pass as the tip stays within `tol_mm` of the planned
polyline (checked at eighths of the line through the forward kinematics), the straight chord
between its ends too (a rotary arc over a whole ring would hold the first: a record of the move's
ends, like the simulator's deposit log, would not), and the tool axis within `axis_tol_deg` of the
planned one; a single planned move that strays is halved in the part frame until its pieces
hold. Lines end where the planned speed changes (more than 2 %), before it drifts more than 2 %
from the line's first (feed-forward), and at the pass's end. A line shorter in time than its
`min_s` (twice its serial time at the link's baud) is split again with its neighbours into lines
of even time; one that cannot (a short piece between two sharp corners) keeps its place and is
given the minimum time (a slower feed over a fraction of a millimetre) rather than refused:
`Lines.stretched` counts them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from controller.motion.kinematics import Trunnion, unit
from controller.motion.post5 import Post5, feed_word, move_line, rotations

_CHECK = np.linspace(0.125, 0.875, 7)   # fractions of a line where the tip is checked
_MAX_DEPTH = 12                          # a planned move halved at most 12 times (4096 pieces)
_MAX_SPAN = 200                          # planned moves one line may cover
SPEED_BREAK = 0.02                       # a line ends where the planned speed changes more than this
# the G-code words carry 3 decimals (mm and degrees: up to ~2 µm at 100 mm from an axis): the
# lines keep a fifth of the chord tolerance for that rounding
ROUNDING_SHARE = 0.8
AXIS_TOL_DEG = 1.0                       # the tool axis within this of the plan along a line
FEED_WORD = 9.0                          # characters of an F word (" F12345.6") in the serial time
MinTime = Callable[[np.ndarray, np.ndarray], float]   # the shortest time of a line from one machine row to another


@dataclass(frozen=True)
class Lines:
    """Line ends of a pass: part points, tool axes, machine axes, and `at`, the position along the
    planned points (k + f: the fraction f of planned move k → k + 1); entry 0 is the start."""

    part: np.ndarray
    axes: np.ndarray
    machine: np.ndarray
    at: np.ndarray
    stretched: int = 0

    @property
    def seg(self) -> np.ndarray:
        """For each line end the index of the planned point it lies on or after."""
        out: np.ndarray = np.floor(self.at + 1e-9).astype(int)
        return out

    def times(self, move_s: np.ndarray, min_s: np.ndarray | float = 0.0) -> np.ndarray:
        """Process seconds of each line from the planned moves' seconds (`move_s`, one per planned
        move): the planned time of the stretch it covers, at least `min_s`."""
        cum = np.concatenate([[0.0], np.cumsum(move_s)])
        k = np.clip(np.floor(self.at + 1e-9).astype(int), 0, len(move_s))
        frac = self.at - k
        pad = np.append(move_s, 0.0)
        c = cum[k] + frac * pad[k]
        out: np.ndarray = np.maximum(np.diff(c), min_s)
        return out


def part_points(tr: Trunnion, m: np.ndarray) -> np.ndarray:
    """The part point under the tool at each machine row X Y Z A S (forward kinematics, vectorised)."""
    u1, u2 = tr.axes()
    inner, outer = (m[:, 3], m[:, 4]) if tr.table == "AB" else (m[:, 4], m[:, 3])
    c2 = -np.asarray(tr.pivot, dtype=float)
    c1 = c2 + np.asarray(tr.offset, dtype=float)
    q = np.einsum("nij,nj->ni", rotations(u2, -outer), m[:, :3] - c2) + c2
    out: np.ndarray = np.einsum("nij,nj->ni", rotations(u1, -inner), q - c1) + c1
    return out


def tool_axes(tr: Trunnion, m: np.ndarray) -> np.ndarray:
    """The tool axis in the part frame at each machine row: M(a, s)ᵀ·(0, 0, 1)."""
    u1, u2 = tr.axes()
    inner, outer = (m[:, 3], m[:, 4]) if tr.table == "AB" else (m[:, 4], m[:, 3])
    z = np.broadcast_to([0.0, 0.0, 1.0], (len(m), 3))
    out: np.ndarray = np.einsum("nij,nj->ni", rotations(u1, -inner), np.einsum("nij,nj->ni", rotations(u2, -outer), z))
    return out


def _nearest(q: np.ndarray, poly: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per query point: distance to the polyline, its nearest segment and the fraction along it."""
    a, b = poly[:-1], poly[1:]
    ab = b - a
    L2 = np.maximum((ab * ab).sum(axis=1), 1e-18)
    t = np.clip(np.einsum("qsk,sk->qs", q[:, None, :] - a[None], ab) / L2, 0.0, 1.0)
    d = np.linalg.norm(a[None] + t[..., None] * ab[None] - q[:, None, :], axis=2)
    s = np.argmin(d, axis=1)
    r = np.arange(len(q))
    return d[r, s], s, t[r, s]


@dataclass
class _Fit:
    """One pass's planned nodes and the checks a candidate line must pass."""

    post: Post5
    pts: np.ndarray
    axes: np.ndarray
    mach: np.ndarray
    tol: float
    axis_cos: float
    seen: dict[tuple[int, int], bool] = field(default_factory=dict)

    def holds(self, p0: np.ndarray, a0: np.ndarray, m0: np.ndarray, inner: np.ndarray,
              p1: np.ndarray, a1: np.ndarray, m1: np.ndarray) -> bool:
        """The machine-linear line m0 → m1 keeps the tip on the planned polyline p0, inner…, p1."""
        tr = self.post.trunnion
        ms = m0 + (m1 - m0) * _CHECK[:, None]
        poly = np.vstack([p0, self.pts[inner], p1])
        pax = np.vstack([a0, self.axes[inner], a1])
        tips = part_points(tr, ms)
        chord = p0 + (p1 - p0) * _CHECK[:, None]   # and the straight chord (a record of the move's ends)
        d, s, t = _nearest(np.vstack([tips, chord]), poly)
        if d.max() > self.tol:
            return False
        s, t = s[:len(ms)], t[:len(ms)]
        want = pax[s] + (pax[s + 1] - pax[s]) * t[:, None]
        want /= np.maximum(np.linalg.norm(want, axis=1, keepdims=True), 1e-12)
        return bool(((tool_axes(tr, ms) * want).sum(axis=1) >= self.axis_cos).all())

    def span_ok(self, i: int, j: int) -> bool:
        key = (i, j)
        if key not in self.seen:
            self.seen[key] = self._span(i, j)
        return self.seen[key]

    def _span(self, i: int, j: int) -> bool:
        return self.holds(self.pts[i], self.axes[i], self.mach[i], np.arange(i + 1, j),
                          self.pts[j], self.axes[j], self.mach[j])

    def pieces(self, k: float, f0: float, p0: np.ndarray, a0: np.ndarray, m0: np.ndarray,
               f1: float, p1: np.ndarray, a1: np.ndarray, m1: np.ndarray, depth: int,
               out: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]) -> None:
        """A move from position k + f0 to k + f1 along the planned moves, halved until every piece
        holds (pieces appended with their positions)."""
        empty = np.empty(0, dtype=int)
        if depth < _MAX_DEPTH and not self.holds(p0, a0, m0, empty, p1, a1, m1):
            pm, am, fm = 0.5 * (p0 + p1), unit(a0 + a1), 0.5 * (f0 + f1)
            mm = self.post.machine(pm[None, :], am[None, :], (float(m0[3]), float(m0[4])))[0]
            self.pieces(k, f0, p0, a0, m0, fm, pm, am, mm, depth + 1, out)
            self.pieces(k, fm, pm, am, mm, f1, p1, a1, m1, depth + 1, out)
            return
        out.append((p1, a1, m1, k + f1))


def _breaks(speeds: np.ndarray) -> np.ndarray:
    """Planned points where a line must end: the speed of the next move differs by more than 2 %."""
    n = len(speeds) + 1
    out = np.zeros(n, dtype=bool)
    out[-1] = True
    if len(speeds) > 1:
        rel = np.abs(np.diff(speeds)) / np.maximum(np.abs(speeds[:-1]), 1e-9)
        out[1:-1] = rel > SPEED_BREAK
    return out


NODE_MM = 0.25                           # candidate line ends every this far along a planned move


def _nodes(post: Post5, pts: np.ndarray, axes: np.ndarray, machine: np.ndarray,
           node_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Candidate line ends: the planned points and points every `node_mm` between them (part
    point, axis, machine axes next to the planned ones, position `at` along the planned moves)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    n = np.maximum(1, np.ceil(seg / node_mm - 1e-9)).astype(int)
    k = np.repeat(np.arange(len(seg)), n)
    f = np.concatenate([np.arange(m) / m for m in n]) if len(n) else np.empty(0)
    at = np.append(k + f, float(len(pts) - 1))
    kk = np.minimum(np.floor(at).astype(int), len(pts) - 2) if len(pts) > 1 else np.zeros(len(at), dtype=int)
    ff = (at - kk)[:, None]
    P = pts[kk] + (pts[kk + 1] - pts[kk]) * ff if len(pts) > 1 else pts.copy()
    A = axes[kk] + (axes[kk + 1] - axes[kk]) * ff if len(pts) > 1 else axes.copy()
    A /= np.maximum(np.linalg.norm(A, axis=1, keepdims=True), 1e-12)
    planned = np.abs(at - np.round(at)) < 1e-12
    M = np.empty((len(at), machine.shape[1]))
    M[planned] = machine[np.round(at[planned]).astype(int)]
    if (~planned).any():   # continuous from the start's angles, as the planned ones are
        M[~planned] = post.machine(P, A, (float(machine[0, 3]), float(machine[0, 4])))[~planned]
    return P, A, M, at


def fit_lines(post: Post5, pts: np.ndarray, axes: np.ndarray, machine: np.ndarray, speeds: np.ndarray,
              tol_mm: float, min_s: MinTime | None = None,
              axis_tol_deg: float = AXIS_TOL_DEG, node_mm: float = NODE_MM) -> Lines:
    """The lines of a pass (module docstring): `pts`, `axes`, `machine` per planned point (table
    frame, no alignment), `speeds` mm/s per planned move, `min_s(machine row)` the shortest time
    a line ending there may take (None: no minimum)."""
    speeds = np.asarray(speeds, dtype=float)
    P, A, M, at = _nodes(post, pts, axes, machine, node_mm)
    fit = _Fit(post, P, A, M, tol_mm, float(np.cos(np.radians(axis_tol_deg))))
    brk = np.zeros(len(at), dtype=bool)
    pb = np.flatnonzero(_breaks(speeds))
    brk[np.searchsorted(at, pb.astype(float) - 1e-9)] = True
    brk[-1] = True
    planned_s = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.maximum(speeds, 1e-9)
    node_s = Lines(P, A, M, at).times(planned_s)   # seconds between consecutive nodes
    stops = np.flatnonzero(brk)
    ends: list[int] = [0]   # nodes the lines end on (before pieces)
    i, n = 0, len(at)
    ns = speeds[np.minimum(np.floor(at + 1e-9).astype(int), len(speeds) - 1)] if len(speeds) else np.ones(n)
    while i < n - 1:
        lim = min(int(stops[np.searchsorted(stops, i, side="right")]), i + _MAX_SPAN)
        drift = np.flatnonzero(np.abs(ns[i + 1:lim] / max(float(ns[i]), 1e-9) - 1.0) > SPEED_BREAK)
        lim = i + 1 + int(drift[0]) if len(drift) and int(drift[0]) > 0 else lim   # the speed drifts > 2 %
        j = _farthest(fit, i, lim)
        ends.append(j)
        i = j
    if min_s is not None:
        ends = _rebalance(fit, ends, brk, node_s, min_s)
    return _emit(fit, at, ends, planned_s, min_s)


def _farthest(fit: _Fit, i: int, lim: int) -> int:
    """The farthest planned point up to `lim` one line from i reaches (galloping, then bisection)."""
    good, bad, step = i + 1, lim + 1, 1
    while good < lim:
        cand = min(good + step, lim)
        if not fit.span_ok(i, cand):
            bad = cand
            break
        good, step = cand, step * 2
    while bad - good > 1:
        mid = (good + bad) // 2
        if fit.span_ok(i, mid):
            good = mid
        else:
            bad = mid
    return good


def _rebalance(fit: _Fit, ends: list[int], brk: np.ndarray, move_s: np.ndarray,
               min_s: MinTime) -> list[int]:
    """A line shorter than its minimum and its neighbours (a window of up to 6 lines, no speed
    change inside) split again into as many or one fewer lines of even time, where they all hold
    and all last their minimum; otherwise it stays (and is given its minimum time)."""
    cum = np.concatenate([[0.0], np.cumsum(move_s)])
    ends = list(ends)
    k = 1
    while k < len(ends):
        a, b = ends[k - 1], ends[k]
        if cum[b] - cum[a] >= min_s(fit.mach[a], fit.mach[b]) or not fit.span_ok(a, b):
            k += 1
            continue
        new = _window(fit, ends, k, brk, cum, min_s)
        if new is None:
            k += 1
            continue
        ends = new
        k = max(1, k - 1)
    return ends


def _window(fit: _Fit, ends: list[int], k: int, brk: np.ndarray, cum: np.ndarray,
            min_s: MinTime) -> list[int] | None:
    """`ends` with the lines around line k (ends[k-1] → ends[k]) split evenly, or None."""
    last = len(ends) - 1
    for w in range(2, 7):
        for k0 in range(max(1, k - w + 1), min(k, last - w + 1) + 1):
            lo, hi = ends[k0 - 1], ends[k0 + w - 1]
            if hi - lo > _MAX_SPAN * 2 or brk[lo + 1:hi].any():
                continue
            for c in (w - 1, w):
                cut = _even(fit, lo, hi, c, cum, min_s)
                if cut is not None:
                    return ends[:k0 - 1] + cut + ends[k0 + w:]
    return None


def _even(fit: _Fit, lo: int, hi: int, c: int, cum: np.ndarray,
          min_s: MinTime) -> list[int] | None:
    """lo → hi in c lines that hold and last their minimum, each cut at the node nearest to an
    even time mark that works (within ±4 nodes, left to right), or None."""
    total = float(cum[hi] - cum[lo])
    cut = [lo]
    for i in range(1, c):
        mark = int(np.searchsorted(cum, cum[lo] + total * i / c))
        for x in sorted(range(mark - 4, mark + 5), key=lambda v: abs(v - mark)):
            if cut[-1] < x < hi and cum[x] - cum[cut[-1]] >= min_s(fit.mach[cut[-1]], fit.mach[x]) and fit.span_ok(cut[-1], x):
                cut.append(x)
                break
        else:
            return None
    if cum[hi] - cum[cut[-1]] < min_s(fit.mach[cut[-1]], fit.mach[hi]) or not fit.span_ok(cut[-1], hi):
        return None
    return cut + [hi]


def _emit(fit: _Fit, at: np.ndarray, ends: list[int], planned_s: np.ndarray,
          min_s: MinTime | None) -> Lines:
    P, A, M, U = [fit.pts[0]], [fit.axes[0]], [fit.mach[0]], [float(at[0])]
    for a, b in zip(ends[:-1], ends[1:]):
        if b - a == 1 and not fit.span_ok(a, b):   # one node-to-node move that strays: its pieces
            out: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]] = []
            fit.pieces(0, float(at[a]), fit.pts[a], fit.axes[a], fit.mach[a], float(at[b]), fit.pts[b],
                       fit.axes[b], fit.mach[b], 0, out)
            for p, ax, m, u in out:
                P.append(p)
                A.append(ax)
                M.append(m)
                U.append(u)
            continue
        P.append(fit.pts[b])
        A.append(fit.axes[b])
        M.append(fit.mach[b])
        U.append(float(at[b]))
    lines = Lines(np.asarray(P), np.asarray(A), np.asarray(M), np.asarray(U))
    if min_s is None:
        return lines
    mins = np.array([min_s(a, b) for a, b in zip(lines.machine[:-1], lines.machine[1:])])
    short = int((lines.times(planned_s) < mins - 1e-12).sum())
    return Lines(lines.part, lines.axes, lines.machine, lines.at, short)


def compact_line(prev: np.ndarray | None, m: np.ndarray, letters: str, feed: float | None = None) -> str:
    """A G1 line with only the axis words that change from `prev` (axis words are modal; F is on
    every line: in inverse time it must be)."""
    full = move_line(m, letters)[3:].split(" ")
    if prev is not None:
        before = move_line(prev, letters)[3:].split(" ")
        words = [w for w, b in zip(full, before) if w != b] or full[:1]
    else:
        words = full
    return "G1 " + " ".join(words) + (f" F{feed_word(feed)}" if feed is not None else "")


def serial_min_s(letters: str, baud: int, factor: float = 2.0) -> MinTime:
    """`factor` × the serial time of the line from one machine row to the next (8N1: 10 bits a
    byte): the words `compact_line` writes, an F word, the newline."""
    words: dict[bytes, list[str]] = {}

    def of(m: np.ndarray) -> list[str]:
        key = m.tobytes()
        if key not in words:
            words[key] = move_line(m, letters)[3:].split(" ")
        return words[key]

    def f(a: np.ndarray, b: np.ndarray) -> float:
        wa, wb = of(a), of(b)
        changed = [len(x) + 1 for x, y in zip(wb, wa) if x != y] or [len(wb[0]) + 1]
        return factor * (2.0 + sum(changed) + FEED_WORD + 1.0) * 10.0 / baud
    return f

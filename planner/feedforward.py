"""Feed-forward along the path (docs/contract.md §3 item 11, docs/along-the-path.md): per-segment speeds
(and wire feeds) that level each layer's predicted top.

A bead's height is not uniform along it even with a perfect model: where two passes of a layer
crowd together (a region that narrows between a square's ring and a round hole's) they lay more
metal on an area than their share, where they part less; a tight turn lays more on its inside; an
open bead's start and end run down. The planner predicts the deposit of a layer from the layer's
own passes with the bead model, in model units:

- every pass is sampled along its centre line every `cell_mm`; each sample pours the metal its
  segment lays per mm (π·D²/4 · WFS / v, the mass balance's own figure) times its length;
- the metal is spread over a disc of the bead's width with Ding's parabola as its profile
  (`1 − (2r/w)²`, unit volume), on a grid of `cell_mm` (an FFT convolution of the poured metal);
- the predicted top along the pass is that height map sampled on the centre line, averaged per
  segment.

Each segment's metal is then scaled by target / predicted (the target: the layer's own mean along
every centre line), filtered along the path over one bead width (the pool smooths anything
shorter), bounded by `max_trim`, renormalised so every bead keeps its planned metal (mass balance
per bead), and predicted again; a few rounds converge. The metal becomes a travel speed per
segment, and where the speed alone would leave the cell's limits, a wire feed inside the
material's envelope. A pass whose segments all stay within `min_change` of its one speed keeps it
(and its points): only the passes that need it are split into segments of at most `step_mm`.

Pure and deterministic: numpy arrays in, frozen dataclasses out, the same job for the same input.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from planner.job import Pass

__all__ = ["FeedForwardOptions", "Envelope", "LayerLevel", "level_layer", "level_summary", "predicted_tops"]


@dataclass(frozen=True)
class FeedForwardOptions:
    """How the feed-forward levels a layer (PlanOptions.feed_forward; None there: off)."""

    step_mm: float | None = None      # longest segment of a levelled pass (None: half the bead width)
    cells_per_width: float = 8.0      # the prediction's grid: cells of width / this (samples at half a cell)
    rounds: int = 4                   # predict-correct rounds
    min_gain_mm: float = 0.02         # a layer whose predicted spread would shrink by less keeps its speeds
    gain: float = 0.7                 # each round corrects this share (in log) of the predicted error
    max_trim: float = 0.45            # the metal per segment within [1 - t, 1 + t] of the pass's own
    smooth_mm: float | None = None    # filter length along the path (None: one bead width)
    min_change: float = 0.01          # a pass whose metal varies less than this keeps its one speed


@dataclass(frozen=True)
class Envelope:
    """Where a segment's speed and wire feed may go: the cell's speeds, the material's wire feeds."""

    speed_min: float
    speed_max: float
    wfs_min: float
    wfs_max: float


@dataclass(frozen=True)
class LayerLevel:
    """The predicted top of one layer along its pass centre lines (max − min, mm), before and after."""

    spread_before_mm: float
    spread_after_mm: float
    passes_levelled: int


@dataclass(frozen=True)
class _Samples:
    """A layer's passes sampled along their centre lines, and the round ends of their pools."""

    xy: np.ndarray        # (N, 2) sample points
    ds: np.ndarray        # (N,) mm of path each sample stands for
    nrm: np.ndarray       # (N, 2) unit normal of the path at each sample
    seg: np.ndarray       # (N,) global segment index of each sample
    seg_pass: np.ndarray  # (S,) pass index of each global segment
    seg_len: np.ndarray   # (S,) segment lengths
    seg_s: np.ndarray     # (S,) mm along its pass of each segment's middle
    seg0: np.ndarray      # (P + 1,) first global segment of each pass
    cap_xy: np.ndarray    # (C, 2) where a pool ends (a bead's start or end, a turn)
    cap_dir: np.ndarray   # (C, 2) unit direction the half disc lies in
    cap_src: np.ndarray   # (K,) samples giving metal to a round end
    cap_of: np.ndarray    # (K,) the round end each gives it to
    cap_frac: np.ndarray  # (K,) the share of the sample's metal it gives


def subdivide(p: Pass, step_mm: float) -> Pass:
    """The pass with every segment longer than `step_mm` cut into equal ones (the same path; tool
    axes and normals blended and normalised); per-segment arrays repeated onto the pieces."""
    pts = p.points
    n = np.maximum(1, np.ceil(np.linalg.norm(np.diff(pts, axis=0), axis=1) / step_mm - 1e-9)).astype(int)
    if np.all(n == 1):
        return p
    seg_of = np.repeat(np.arange(len(n)), n)
    first = np.cumsum(n) - n
    f = np.r_[(np.arange(len(seg_of)) - first[seg_of]) / n[seg_of], 1.0]
    i0 = np.r_[seg_of, len(pts) - 2]

    def blend(a: np.ndarray | None, unit: bool) -> np.ndarray | None:
        if a is None:
            return None
        out: np.ndarray = a[i0] + (a[i0 + 1] - a[i0]) * f[:, None]
        if unit:
            out = out / np.maximum(np.linalg.norm(out, axis=1), 1e-12)[:, None]
        return out

    sp = None if p.seg_speed_mm_min is None else p.seg_speed_mm_min[seg_of]
    wf = None if p.seg_wfs_m_min is None else p.seg_wfs_m_min[seg_of]
    new_pts = blend(pts, False)
    assert new_pts is not None
    return Pass(p.role, p.width_mm, p.current_a, p.speed_mm_min, p.wfs_m_min, new_pts, blend(p.normals, True),
                blend(p.axes, True), p.inside_envelope, sp, wf)


def _sample(passes: tuple[Pass, ...], cell: float, width: float) -> _Samples:
    """Every pass sampled along its centre line at about `cell` mm (all passes at once: each
    pass's lengths shifted past the previous pass's, so one sorted search finds every segment)."""
    pts_of = [p.points[:, :2] for p in passes]
    npts = np.array([len(q) for q in pts_of])
    P = np.concatenate(pts_of)
    nseg = npts - 1
    seg0 = np.r_[0, np.cumsum(nseg)]
    seg_pass = np.repeat(np.arange(len(passes)), nseg)
    a_idx = np.arange(seg0[-1]) + np.repeat(np.r_[0, np.cumsum(npts)][:-1] - seg0[:-1], nseg)
    A, B = P[a_idx], P[a_idx + 1]
    lens = np.linalg.norm(B - A, axis=1)
    cg = np.r_[0.0, np.cumsum(lens)]
    total = cg[seg0[1:]] - cg[seg0[:-1]]
    cum0 = cg[:-1] - cg[seg0[:-1]][seg_pass]            # each segment's start along its pass
    n = np.maximum(1, np.ceil(total / cell)).astype(np.int64)
    first = np.r_[0, np.cumsum(n)]
    sp = np.repeat(np.arange(len(passes)), n)
    step = total / n
    s = (np.arange(first[-1]) - first[:-1][sp] + 0.5) * step[sp]
    shift = np.r_[0.0, np.cumsum(total + 1.0)][:-1]      # pass p's lengths start at shift[p]
    key = s + shift[sp]
    k = np.searchsorted(cum0 + shift[seg_pass], key, side="right") - 1
    k = np.clip(k, seg0[:-1][sp], seg0[1:][sp] - 1)
    t = (s - cum0[k]) / np.maximum(lens[k], 1e-12)
    u = (B - A) / np.maximum(lens, 1e-12)[:, None]
    xy = A[k] + (B[k] - A[k]) * t[:, None]
    caps = _caps(width, P, a_idx, u, lens, seg0, seg_pass, cum0, total, shift, key, first)
    return _Samples(xy, step[sp], np.column_stack([-u[k, 1], u[k, 0]]), k, seg_pass, lens, cum0 + 0.5 * lens,
                    seg0, *caps)


TURN_DEG = 20.0   # a turn sharper than this ends one pool and starts the next (round ends)
CHUNK_MM = 1.0    # the metal of a pool's last mm spreads over its round end


def _caps(width: float, P: np.ndarray, a_idx: np.ndarray, u: np.ndarray, lens: np.ndarray, seg0: np.ndarray,
          seg_pass: np.ndarray, cum0: np.ndarray, total: np.ndarray, shift: np.ndarray, key: np.ndarray,
          first: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The round ends of the pools: at a bead's start and end, and where its path turns by more
    than `TURN_DEG` (the pool of the leg before ends there, the next one's starts), the metal of
    the last `CHUNK_MM` spreads over a half disc as well as over its strip of the bead. Each round
    end takes from a run of samples of its pass (sorted by `key`): their index ranges."""
    c = CHUNK_MM
    r = width / 2.0
    a_cap = math.pi * r ** 2 / 2.0
    frac = a_cap / (a_cap + width * c)
    last = seg0[1:] - 1
    ss = np.searchsorted
    # the starts and the ends of the beads
    at = [P[a_idx[seg0[:-1]]], P[a_idx[last] + 1]]
    dirs = [-u[seg0[:-1]], u[last]]
    lo = [first[:-1], ss(key, shift + total - c, side="right")]
    hi = [ss(key, shift + c, side="left"), first[1:]]
    # the turns inside a pass (between segment j and j + 1)
    j = np.flatnonzero(seg_pass[:-1] == seg_pass[1:]) if len(seg_pass) > 1 else np.zeros(0, dtype=np.int64)
    cos = np.clip(np.sum(u[j] * u[j + 1], axis=1), -1.0, 1.0)
    j = j[(np.degrees(np.arccos(cos)) > TURN_DEG) & (lens[j] > 1e-9) & (lens[j + 1] > 1e-9)]
    pos = cum0[j + 1] + shift[seg_pass[j + 1]]
    at += [P[a_idx[j + 1]], P[a_idx[j + 1]]]
    dirs += [u[j], -u[j + 1]]
    lo += [ss(key, pos - c, side="right"), ss(key, pos, side="right")]
    hi += [ss(key, pos, side="right"), ss(key, pos + c, side="left")]
    at_all, dir_all = np.concatenate(at), np.concatenate(dirs)
    lo_all, hi_all = np.concatenate(lo), np.concatenate(hi)
    keep = hi_all > lo_all
    at_all, dir_all, lo_all, hi_all = at_all[keep], dir_all[keep], lo_all[keep], hi_all[keep]
    cnt = hi_all - lo_all
    ends = np.cumsum(cnt)
    src = np.arange(int(ends[-1]) if len(ends) else 0) - np.repeat(ends - cnt - lo_all, cnt)
    return at_all.reshape(-1, 2), dir_all.reshape(-1, 2), src, np.repeat(np.arange(len(cnt)), cnt), np.full(len(src), frac)


class _Grid:
    """The layer's prediction grid: each sample's metal across its bead in Ding's parabola, the
    round ends' over half discs with the same profile, onto cells of `cell` mm.

    The splat is linear in the metal, so its entries are built once per layer (per sample and per
    round end, the cells it pours into and their weights per unit of metal); a round is one
    weighted `np.bincount` over them (a sparse product in plain numpy: `cell plan` need not import
    scipy, whose import alone costs more than planning a small part)."""

    ACROSS = 15          # points across a bead (half a cell apart at 8 cells a width)
    RINGS, RAYS = 5, 11  # a half disc's polar points

    def __init__(self, smp: _Samples, width: float, cell: float) -> None:
        r = width / 2.0
        self.smp, self.cell = smp, cell
        d = np.linspace(-r, r, self.ACROSS + 2)[1:-1]
        w = 1.0 - (d / r) ** 2
        w_across = w / w.sum()
        rr = (np.arange(self.RINGS) + 0.5) / self.RINGS * r
        th = np.linspace(-np.pi / 2, np.pi / 2, self.RAYS + 2)[1:-1]
        R, T = np.meshgrid(rr, th)
        wq = (1.0 - (R / r) ** 2) * R
        w_cap = (wq / wq.sum()).ravel()
        strip = smp.xy[:, None, :] + smp.nrm[:, None, :] * d[None, :, None]
        cx, cy = smp.cap_dir[:, 0:1], smp.cap_dir[:, 1:2]
        px, py = (R * np.cos(T)).ravel()[None, :], (R * np.sin(T)).ravel()[None, :]
        cap = np.stack([smp.cap_xy[:, 0:1] + cx * px - cy * py, smp.cap_xy[:, 1:2] + cy * px + cx * py], axis=-1)
        # the box of every point (a strip's ends bound it: each strip is a straight line across)
        ends = [strip[:, 0], strip[:, -1], cap.reshape(-1, 2), smp.xy]
        self.lo = np.min([e.min(axis=0) for e in ends if len(e)], axis=0) - 2 * cell
        hi = np.max([e.max(axis=0) for e in ends if len(e)], axis=0) + 2 * cell
        self.shape = (int(math.ceil((hi[1] - self.lo[1]) / cell)) + 2, int(math.ceil((hi[0] - self.lo[0]) / cell)) + 2)
        # each point to its nearest cell (the model's resolution is the bead's, not the cell's)
        strip_cells, cap_cells = self._cell(strip.reshape(-1, 2)), self._cell(cap.reshape(-1, 2))
        n, c = len(smp.xy), len(smp.cap_xy)
        self.data = np.concatenate([np.tile(w_across, n), np.tile(w_cap, c)]) / (cell * cell)
        self.rows = np.concatenate([strip_cells, cap_cells])
        self.cols = np.concatenate([np.repeat(np.arange(n), self.ACROSS), n + np.repeat(np.arange(c), len(w_cap))])
        u = (smp.xy - self.lo) / cell
        i0 = np.floor(u).astype(np.int64)
        fx, fy = u[:, 0] - i0[:, 0], u[:, 1] - i0[:, 1]
        self.at = (i0[:, 1], i0[:, 0], fx, fy, 1 - fx, 1 - fy)

    def _cell(self, p: np.ndarray) -> np.ndarray:
        ij = np.rint((p - self.lo) / self.cell).astype(np.int64)
        out: np.ndarray = ij[:, 1] * self.shape[1] + ij[:, 0]
        return out

    def heights(self, volume: np.ndarray) -> np.ndarray:
        """The predicted height at every sample of the volumes poured at the samples."""
        smp = self.smp
        moved = volume[smp.cap_src] * smp.cap_frac
        strip_v = volume - np.bincount(smp.cap_src, weights=moved, minlength=len(volume))
        cap_v = np.bincount(smp.cap_of, weights=moved, minlength=len(smp.cap_xy))
        metal = np.concatenate([strip_v, cap_v])
        g = np.bincount(self.rows, weights=self.data * metal[self.cols],
                        minlength=self.shape[0] * self.shape[1]).reshape(self.shape)
        # a [1 2 1] / 4 filter each way takes out the aliasing of points onto their nearest cells
        g[:, 1:-1] = 0.25 * g[:, :-2] + 0.5 * g[:, 1:-1] + 0.25 * g[:, 2:]
        g[1:-1, :] = 0.25 * g[:-2, :] + 0.5 * g[1:-1, :] + 0.25 * g[2:, :]
        j, i, fx, fy, gx, gy = self.at
        out: np.ndarray = (g[j, i] * gx * gy + g[j, i + 1] * fx * gy
                           + g[j + 1, i] * gx * fy + g[j + 1, i + 1] * fx * fy)
        return out


def _per_segment(values: np.ndarray, smp: _Samples) -> np.ndarray:
    """Sample values averaged per segment (by the path each sample stands for)."""
    n = len(smp.seg_len)
    w = np.bincount(smp.seg, weights=smp.ds, minlength=n)
    v = np.bincount(smp.seg, weights=values * smp.ds, minlength=n)
    out: np.ndarray = np.where(w > 0, v / np.maximum(w, 1e-12), np.nan)
    # a segment shorter than a sample's spacing holds none: its neighbour's value
    idx = np.where(np.isfinite(out), np.arange(n), 0)
    np.maximum.accumulate(idx, out=idx)
    filled: np.ndarray = out[idx]
    return np.where(np.isfinite(filled), filled, np.nanmean(out))


def _smooth(values: np.ndarray, smp: _Samples, length: float) -> np.ndarray:
    """Each pass's per-segment values averaged over `length` mm of its path (a moving window by
    length; all passes at once: each pass's positions shifted past the previous pass's window)."""
    L = smp.seg_len
    c_w = np.r_[0.0, np.cumsum(L)]
    c_v = np.r_[0.0, np.cumsum(L * values)]
    totals = np.bincount(smp.seg_pass, weights=L, minlength=len(smp.seg0) - 1)
    shift = np.r_[0.0, np.cumsum(totals + length + 1.0)][smp.seg_pass]
    s = smp.seg_s + shift
    lo = np.searchsorted(s, s - length / 2, side="left")
    hi = np.searchsorted(s, s + length / 2, side="right")
    out: np.ndarray = (c_v[hi] - c_v[lo]) / np.maximum(c_w[hi] - c_w[lo], 1e-12)
    return out


def predicted_tops(passes: tuple[Pass, ...], wire_diameter_mm: float, cells_per_width: float = 8.0) -> list[np.ndarray]:
    """The predicted top (mm above the layer's base) of every segment of every pass, each at its
    planned speed and wire feed."""
    width = max(p.width_mm for p in passes)
    cell_mm = width / cells_per_width
    smp = _sample(passes, cell_mm / 2, width)
    grid = _Grid(smp, width, cell_mm)
    h = _per_segment(grid.heights(_metal(passes, smp, wire_diameter_mm) * smp.ds), smp)
    return [h[a:b] for a, b in zip(smp.seg0[:-1], smp.seg0[1:])]


def _metal(passes: tuple[Pass, ...], smp: _Samples, wire_diameter_mm: float) -> np.ndarray:
    """mm² of metal per mm of travel at every sample (π·D²/4 · WFS / v of its segment)."""
    area = np.concatenate([p.wire_feeds() / p.speeds() for p in passes]) * (math.pi * wire_diameter_mm ** 2 / 4 * 1000)
    out: np.ndarray = area[smp.seg]
    return out


def _spread(tops: np.ndarray, lengths: np.ndarray) -> float:
    keep = lengths > 1e-9
    return float(tops[keep].max() - tops[keep].min()) if np.any(keep) else 0.0


def level_layer(passes: tuple[Pass, ...], wire_diameter_mm: float, env: Envelope,
                opts: FeedForwardOptions = FeedForwardOptions()) -> tuple[tuple[Pass, ...], LayerLevel]:
    """The layer's passes with per-segment speeds (and wire feeds) that level its predicted top."""
    if not passes or any(p.axes is not None for p in passes):
        return passes, LayerLevel(0.0, 0.0, 0)   # 5-axis passes: not levelled (their beads lean)
    width = max(p.width_mm for p in passes)
    cut = tuple(subdivide(p, opts.step_mm or width / 2.0) for p in passes)
    best, before, after, seg0 = _level_rounds(cut, wire_diameter_mm, opts)
    out, n = _apply(cut, passes, best, seg0, env, opts.min_change)
    if n == 0 or after > before - opts.min_gain_mm:
        return passes, LayerLevel(before, before, 0)
    return out, LayerLevel(before, after, n)


_Levelled = tuple[np.ndarray, float, float, np.ndarray]


def _level_rounds(cut: tuple[Pass, ...], wire_diameter_mm: float, opts: FeedForwardOptions) -> _Levelled:
    """Predict, correct, predict again (`opts.rounds`): the best metal multipliers per segment, the
    predicted spread before and after, the first segment of each pass."""
    width = max(p.width_mm for p in cut)
    cell_mm = width / opts.cells_per_width
    smp = _sample(cut, cell_mm / 2, width)
    grid = _Grid(smp, width, cell_mm)
    metal = _metal(cut, smp, wire_diameter_mm)
    seg_metal = np.bincount(smp.seg, weights=metal * smp.ds, minlength=len(smp.seg_len)) / np.maximum(smp.seg_len, 1e-12)
    seg_metal = np.where(smp.seg_len > 1e-12, seg_metal, 1.0)
    m = best = np.ones(len(smp.seg_len))
    lo, hi = 1.0 - opts.max_trim, 1.0 + opts.max_trim
    before = after = 0.0
    for r in range(opts.rounds + 1):
        h = _per_segment(grid.heights(metal * m[smp.seg] * smp.ds), smp)
        spread = _spread(h, smp.seg_len)
        if r == 0:
            before = after = spread
        elif spread < after:     # the best round is kept (a bead's end may not be levelled by speed)
            best, after = m, spread
        if r == opts.rounds:
            break
        target = float(np.sum(h * smp.seg_len) / np.sum(smp.seg_len))
        f = _smooth(target / np.maximum(h, 1e-6 * target), smp, opts.smooth_mm or width)
        m = _balanced(np.clip(m * f ** opts.gain, lo, hi), smp, seg_metal, lo, hi)
    return best, before, after, smp.seg0


def _balanced(m: np.ndarray, smp: _Samples, seg_metal: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Every pass's multipliers scaled so it lays its planned metal (then clipped; a few times)."""
    out = m.copy()
    n_pass = len(smp.seg0) - 1
    base = seg_metal * smp.seg_len
    want = np.bincount(smp.seg_pass, weights=base, minlength=n_pass)
    busy = np.ones(n_pass, dtype=bool)
    for _ in range(4):
        k = want / np.maximum(np.bincount(smp.seg_pass, weights=base * out, minlength=n_pass), 1e-12)
        on = busy[smp.seg_pass]
        out[on] = np.clip(out[on] * k[smp.seg_pass][on], lo, hi)
        busy &= np.abs(k - 1.0) >= 1e-4
        if not busy.any():
            break
    return out


def _apply(cut: tuple[Pass, ...], orig: tuple[Pass, ...], m: np.ndarray, seg0: np.ndarray, env: Envelope,
           min_change: float) -> tuple[tuple[Pass, ...], int]:
    """Metal multipliers to per-segment speeds (and wire feeds past the speed limits)."""
    out, n = [], 0
    for pi, (p, p0) in enumerate(zip(cut, orig)):
        mm = m[seg0[pi]:seg0[pi + 1]]
        if float(np.max(np.abs(mm - 1.0))) < min_change:
            out.append(p0)
            continue
        v0, w0 = p.speeds(), p.wire_feeds()
        v = np.clip(v0 / mm, env.speed_min, env.speed_max)
        w = np.clip(w0 * mm * v / v0, env.wfs_min, env.wfs_max)   # what the speed could not do
        same = bool(np.all(np.abs(w - w0) <= 1e-8 + 1e-6 * np.abs(w0)))   # np.allclose(w, w0, rtol=1e-6)
        new_w = None if same and p.seg_wfs_m_min is None else w
        out.append(p.with_process(np.round(v, 1), None if new_w is None else np.round(new_w, 3)))
        n += 1
    return tuple(out), n


def level_summary(levels: list[LayerLevel]) -> dict[str, object]:
    """The plan summary's `feed_forward`: the predicted top's spread per layer, before and after (mm)."""
    before = [round(lv.spread_before_mm, 3) for lv in levels]
    after = [round(lv.spread_after_mm, 3) for lv in levels]
    return {"spread_before_mm": before, "spread_after_mm": after,
            "worst_before_mm": max(before, default=0.0), "worst_after_mm": max(after, default=0.0),
            "passes_levelled": sum(lv.passes_levelled for lv in levels)}

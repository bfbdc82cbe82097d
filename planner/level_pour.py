"""The poured feed-forward (docs/along-the-path.md "The poured prediction"; opt-in: PlanOptions.feed_forward_pour):
per-segment speeds and wire feeds that bring each layer's predicted top level.

A bead's height is not uniform along it even with a perfect model: where two passes of a layer
crowd together (a region that narrows between a square's ring and a round hole's) they lay more
metal on an area than their share, where they part less; a bead's flank over a gap runs into it;
a bead's start and end pour their round ends; and what one layer leaves uneven the next one is
laid on. The planner carries the predicted top of the stack from layer to layer
(planner/pour.py: the metal poured as the simulated world pours it, level-filling each pool's
footprint, held by Ding's parabola) and lays every pass of a layer on it in the layer's order:

- on a layer of two beads or more, the stack's departures from its level carried to the next layer
  only in part (`carry`): the model's residual where beads meet (a wedge between rings it sees
  deepen more than the world does) would otherwise pile up layer on layer and be levelled as if it
  were there; a lone bead's (a wall's ends, which the model fits) are carried whole;
- the layer's level: the mean top its passes would reach as planned, laid on the stack;
- each pool's metal is what brings its cells to that level (the volume between the predicted
  surface and min(level, parabola), closed form), shared by its chunks; a segment's is its
  chunks' (a few rounds: the metal changes the parabola's peak, the speed the bead's width);
- within `max_trim` of the pass's own metal; the metal becomes a travel speed per segment, and
  where the speed would leave the cell's limits, a wire feed inside the material's envelope;
- the pass is then poured with the metal it can lay, and the next pass laid on it.

A pass whose segments all stay within `min_change` of its one speed keeps it (and its points):
only the passes that need it are split into segments of at most `step_mm`. A layer whose
predicted spread would not shrink by `min_gain_mm` keeps its single speeds (and the stack takes
that layer as planned).

Pure and deterministic: numpy arrays in, frozen dataclasses out, the same job for the same input.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from planner.feedforward import Envelope, LayerLevel, subdivide
from planner.job import Pass
from planner.pour import BeadLaw, Footprint, Stack, footprint

__all__ = ["BeadLaw", "PourOptions", "Stack", "level_layer", "predicted_tops"]


@dataclass(frozen=True)
class PourOptions:
    """How the poured feed-forward levels a layer (PlanOptions.feed_forward_pour)."""

    step_mm: float | None = None      # longest segment of a levelled pass (None: half the bead width)
    rounds: int = 6                   # metal-width rounds per pass
    gain: float = 1.0                 # each round moves this share (in log) to the metal asked (the width follows)
    min_gain_mm: float = 0.02         # a layer whose predicted spread would shrink by less keeps its speeds
    max_trim: float = 1.5             # the metal per segment within [max(1 - t, 0.1), 1 + t] of the pass's own
    min_change: float = 0.01          # a pass whose metal varies less than this keeps its one speed
    turn_mm: float = 1.0              # a turn's own segments (its outside's round end takes their metal)
    round_mm: float = 0.25            # a sharp turn rounded with this radius, in bead widths (0: not rounded)
    layer_rounds: int = 1             # the layer laid again with what the later passes add taken off
    carry: float = 0.3                # the stack's departures from its level believed this much by a layer of >= 2 beads
    carry_band_mm: float = 3.0        # (its cells within this of the level: a wall's flanks stay as they are)


CELL_MM = 0.5     # the predicted stack's cells
POOL_WIDTHS = 2.0   # a pool levels out over this many bead widths behind the arc (the world: sims/heightmap.py)
TURN_DEG = 20.0   # a sharper turn gets short segments of its own


def _at_turns(p: Pass, length: float) -> Pass:
    """The pass with a point `length` mm before and after every turn sharper than TURN_DEG (the
    same path): the outside of a turn takes a pool's round end, which only the metal laid right
    there can fill."""
    pts = p.points
    d = np.diff(pts[:, :2], axis=0)
    lens = np.hypot(d[:, 0], d[:, 1])
    u = d / np.maximum(lens, 1e-12)[:, None]
    cos = np.sum(u[:-1] * u[1:], axis=1)
    turn = np.flatnonzero((cos < math.cos(math.radians(TURN_DEG))) & (lens[:-1] > 1e-9) & (lens[1:] > 1e-9)) + 1
    if len(turn) == 0 or p.axes is not None:
        return p
    cuts: list[tuple[int, float]] = []    # (segment, fraction along it)
    for k in turn.tolist():
        if lens[k - 1] > 1.5 * length:
            cuts.append((k - 1, 1.0 - length / float(lens[k - 1])))
        if lens[k] > 1.5 * length:
            cuts.append((k, length / float(lens[k])))
    if not cuts:
        return p
    seg = np.array([c[0] for c in cuts])
    frac = np.array([c[1] for c in cuts])
    order = np.argsort(np.r_[np.arange(len(pts)), seg + frac], kind="stable")

    def blend(a: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.vstack([a, a[seg] + (a[seg + 1] - a[seg]) * frac[:, None]])[order]
        return out

    src = np.r_[np.arange(len(pts)), seg][order][:-1]     # each new segment's old one
    src = np.minimum(src, len(lens) - 1)
    normals = None
    if p.normals is not None:
        normals = blend(p.normals)
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1), 1e-12)[:, None]
    sp = None if p.seg_speed_mm_min is None else p.seg_speed_mm_min[src]
    wf = None if p.seg_wfs_m_min is None else p.seg_wfs_m_min[src]
    return Pass(p.role, p.width_mm, p.current_a, p.speed_mm_min, p.wfs_m_min, blend(pts), normals, None,
                p.inside_envelope, sp, wf)


ROUND_DEG = 25.0     # a turn sharper than this is rounded (planner/level_pour.py _rounded)
ARC_DEG = 22.5       # the largest turn between two points of a rounded corner


def _rounded(p: Pass, radius: float) -> Pass:
    """The pass with every turn sharper than ROUND_DEG rounded by an arc of `radius` (its centre
    line cut by radius·(1/cos(θ/2) − 1) at the corner: 0.41·radius at 90°), in steps of at most
    ARC_DEG. The outside of a turn takes the round end of the pool that reaches it, which only the
    metal laid right there fills: one turn of 90° needs about 2.5 × a chunk's metal there (more
    than a bead of the same width can lay), four of 22.5° about 1.4 × each."""
    pts = p.points
    if p.axes is not None or len(pts) < 3:
        return p
    d = np.diff(pts[:, :2], axis=0)
    lens = np.hypot(d[:, 0], d[:, 1])
    u = d / np.maximum(lens, 1e-12)[:, None]
    turn = np.arccos(np.clip(np.sum(u[:-1] * u[1:], axis=1), -1.0, 1.0))
    tan_len = radius * np.tan(turn / 2.0)
    sharp = np.flatnonzero((np.degrees(turn) > ROUND_DEG) & (lens[:-1] > 1e-9) & (lens[1:] > 1e-9)
                           & (tan_len <= 0.45 * np.minimum(lens[:-1], lens[1:]))) + 1
    if len(sharp) == 0:
        return p
    out_pts: list[np.ndarray] = []
    out_nrm: list[np.ndarray] = []
    last = 0
    for k in sharp.tolist():
        out_pts.append(pts[last:k])
        th, tl = float(turn[k - 1]), float(tan_len[k - 1])
        n = int(math.ceil(math.degrees(th) / ARC_DEG))
        a = pts[k, :2] - u[k - 1] * tl            # where the arc leaves the leg before
        side = math.copysign(1.0, float(u[k - 1, 0] * u[k, 1] - u[k - 1, 1] * u[k, 0]))
        centre = a + side * radius * np.array([-u[k - 1, 1], u[k - 1, 0]])
        ang = math.atan2(a[1] - centre[1], a[0] - centre[0]) + side * th * np.arange(n + 1) / n
        out_pts.append(np.column_stack([centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang),
                                        np.full(n + 1, pts[k, 2])]))
        if p.normals is not None:
            out_nrm += [p.normals[last:k], np.repeat(p.normals[k:k + 1], n + 1, axis=0)]
        last = k + 1
    out_pts.append(pts[last:])
    normals = None if p.normals is None else np.vstack(out_nrm + [p.normals[last:]])
    return Pass(p.role, p.width_mm, p.current_a, p.speed_mm_min, p.wfs_m_min, np.vstack(out_pts), normals, None,
                p.inside_envelope)


def _process(v0: np.ndarray, f0: np.ndarray, m: np.ndarray, env: Envelope, law: BeadLaw) -> tuple[np.ndarray, np.ndarray]:
    """Metal multipliers to speeds and wire feeds that keep every segment's width (a little under
    its planned one: the current follows the stick-out). Ribeiro: slower is wider, less current
    narrower, so more metal is a slower bead at a lower wire feed, less a faster one at a higher;
    a bead laid wider than the layer below pours its metal down that layer's sides, one laid
    narrower leaves its flanks behind. Past the envelope's wire feeds: the width gives (narrower for
    less metal; for more, no slower than the width allows: less metal than asked). Then the cell's
    speed limits, the wire feed taking what they leave."""
    keep = law.width(f0, v0) * NARROWER
    lo, hi = np.full(len(m), env.wfs_min), np.full(len(m), env.wfs_max)
    for _ in range(24):   # width(f, f·v0/(m·f0)) rises with f
        mid = 0.5 * (lo + hi)
        wide = law.width(mid, mid * v0 / (m * f0)) > keep
        hi, lo = np.where(wide, mid, hi), np.where(wide, lo, mid)
    f = 0.5 * (lo + hi)
    v = np.maximum(f * v0 / (m * f0), law.speed_for(keep, f))    # never wider than kept
    v = np.clip(v, env.speed_min, env.speed_max)
    f = np.clip(np.minimum(f, m * f0 * v / v0), env.wfs_min, env.wfs_max)
    return v, f


def _wire(wire_diameter_mm: float) -> float:
    """mm² of metal per mm of travel per (m/min of wire / mm/min of travel)."""
    return math.pi * wire_diameter_mm ** 2 / 4.0 * 1000.0


NARROWER = 0.97   # a slower bead kept this much narrower than planned (its current varies with the stick-out)
_Laid = tuple[np.ndarray, np.ndarray, np.ndarray, Footprint]


def _lay(p: Pass, fp: Footprint, stack: Stack, wire: float, law: BeadLaw, env: Envelope, opts: PourOptions,
         target: np.ndarray | None) -> _Laid:
    """Lay one pass on the stack (levelled to `target` per chunk, or as planned: None): its metal
    multipliers, speeds and wire feeds per segment, its footprint."""
    v0, f0 = p.speeds(), p.wire_feeds()
    a0 = wire * f0 / v0
    m = np.ones(len(v0))
    if target is not None:
        lengths = fp.path_of(len(v0))
        lo, hi = max(1.0 - opts.max_trim, 0.1), 1.0 + opts.max_trim
        for _ in range(opts.rounds):
            v, f = _process(v0, f0, m, env, law)
            width = law.width(f, v)
            want = np.maximum(fp.need(stack, target, wire * f / v, width) / np.maximum(lengths, 1e-12),
                              fp.reach(stack, target, width))
            m = np.where(lengths > 1e-9, np.clip(m ** (1.0 - opts.gain) * (want / a0) ** opts.gain, lo, hi), 1.0)
    v, f = _process(v0, f0, m, env, law) if target is not None else (v0, f0)
    fp.commit(stack, fp.pour(stack, wire * f / v, law.width(f, v), None if target is None else float(target.mean())))
    return m, v, f, fp


class _Layer:
    """A layer laid on a stack: what each pass laid, each pass's top right after it and after all."""

    def __init__(self, cut: tuple[Pass, ...], fps: list[Footprint], stack: Stack, wire: float, law: BeadLaw,
                 env: Envelope, opts: PourOptions, targets: list[np.ndarray] | None) -> None:
        self.laid: list[_Laid] = []
        self.own: list[np.ndarray] = []
        for k, (p, fp) in enumerate(zip(cut, fps)):
            self.laid.append(_lay(p, fp, stack, wire, law, env, opts, None if targets is None else targets[k]))
            self.own.append(fp.tops(stack))
        self.final = [fp.tops(stack) for fp in fps]
        tops = np.concatenate(self.final) if fps else np.zeros(1)
        lens = np.concatenate([fp.chunk_len for fp in fps]) if fps else np.ones(1)
        self.spread = float(np.ptp(tops))
        self.mean = float(np.sum(tops * lens) / max(float(np.sum(lens)), 1e-12))

    def targets(self, level: float) -> list[np.ndarray]:
        """Each pass's level per chunk so that the layer stands at `level` once the later passes
        have added what they add on it (a ring laid beside another where the region narrows)."""
        return [level - np.maximum(f - o, 0.0) for f, o in zip(self.final, self.own)]


def level_layer(passes: tuple[Pass, ...], wire_diameter_mm: float, env: Envelope, law: BeadLaw, stack: Stack,
                opts: PourOptions = PourOptions()) -> tuple[tuple[Pass, ...], LayerLevel]:
    """The layer's passes with per-segment speeds (and wire feeds) that bring its predicted top level,
    laid on the predicted stack (which then holds this layer too)."""
    if not passes or any(p.axes is not None for p in passes):
        return passes, LayerLevel(0.0, 0.0, 0)   # 5-axis passes: not levelled (their beads lean)
    width = max(p.width_mm for p in passes)
    step = opts.step_mm or width / 2.0
    cut = tuple(_at_turns(subdivide(_rounded(p, opts.round_mm * width), step), opts.turn_mm) for p in passes)
    wire = _wire(wire_diameter_mm)
    widths = [law.width(p.wire_feeds(), p.speeds()) for p in cut]   # none laid wider (_process)
    reach = max(float(w.max()) for w in widths) / 2.0
    allp = np.concatenate([p.points[:, :2] for p in cut])
    lo = np.floor((allp.min(axis=0) - reach) / stack.cell).astype(int) - 1
    hi = np.floor((allp.max(axis=0) + reach) / stack.cell).astype(int) + 1
    stack.ensure(int(lo[0]), int(hi[0]), int(lo[1]), int(hi[1]))     # the grid the footprints index
    if len(cut) > 1:   # the model's own residual where beads meet does not pile up (a lone bead's: whole)
        stack.relax(opts.carry, opts.carry_band_mm)
    fps = [footprint(stack, p.points[:, :2], w, POOL_WIDTHS * p.width_mm) for p, w in zip(cut, widths)]
    plain = stack.copy()
    as_planned = _Layer(cut, fps, plain, wire, law, env, opts, None)
    before, level = as_planned.spread, as_planned.mean
    best, best_stack = as_planned, plain
    targets = [np.full(len(fp.centre), level) for fp in fps]
    for _ in range(opts.layer_rounds if len(cut) > 1 else 1):   # a lone pass: nothing laid after it
        trial = stack.copy()
        lay = _Layer(cut, fps, trial, wire, law, env, opts, targets)
        if best is as_planned or lay.spread < best.spread:
            best, best_stack = lay, trial
        targets = lay.targets(level)
    stack.take(best_stack)
    if best is as_planned:
        return passes, LayerLevel(before, before, 0)
    out, n = _apply(cut, passes, best.laid, opts.min_change)
    if n == 0 or best.spread > before - opts.min_gain_mm:
        stack.take(plain)
        return passes, LayerLevel(before, before, 0)
    return out, LayerLevel(before, best.spread, n)


def predicted_tops(passes: tuple[Pass, ...], wire_diameter_mm: float, law: BeadLaw, base_z: float,
                   cell_mm: float = 0.5) -> list[np.ndarray]:
    """The predicted top (absolute z) at every ~1 mm of every pass, laid as planned on a flat base."""
    stack = Stack(cell_mm, base_z)
    env = Envelope(1e-6, 1e9, 1e-6, 1e9)
    out = []
    for p in passes:
        fp = footprint(stack, p.points[:, :2], law.width(p.wire_feeds(), p.speeds()), POOL_WIDTHS * p.width_mm)
        _lay(p, fp, stack, _wire(wire_diameter_mm), law, env, PourOptions(), None)
        out.append(fp.tops(stack))
    return out


def _apply(cut: tuple[Pass, ...], orig: tuple[Pass, ...], laid: list[_Laid],
           min_change: float) -> tuple[tuple[Pass, ...], int]:
    """The passes with the speeds (and wire feeds) they were laid with; a pass whose metal varies by
    less than `min_change` keeps its one speed and its points."""
    out, n = [], 0
    for p, p0, (m, v, w, _) in zip(cut, orig, laid):
        if float(np.max(np.abs(m - 1.0))) < min_change:
            out.append(p0)
            continue
        w0 = p.wire_feeds()
        same = bool(np.all(np.abs(w - w0) <= 1e-8 + 1e-6 * np.abs(w0)))   # np.allclose(w, w0, rtol=1e-6)
        new_w = None if same and p.seg_wfs_m_min is None else w
        out.append(p.with_process(np.round(v, 1), None if new_w is None else np.round(new_w, 3)))
        n += 1
    return tuple(out), n

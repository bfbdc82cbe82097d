"""The feed-forward's levelling of a layer reused for a later layer that gives it the same inputs
(issue 40 item 3: wall time), docs/plan-speed.md.

A prismatic part's layers repeat (planner.plan's layer memo plans them the same); their seams
move on layer by layer, but on a loop of few vertices they come back to the same vertex, so many
layers hand the feed-forward (planner/feedforward.py, `level_layer`) passes that differ only in
their height and their boundary normals (a contour point between two facets takes either's): the
box at 4 mm levels 85 distinct layers in 216, the cylinder 210 in 462. What `level_layer` gives
depends on its arguments alone (a pure function) and it levels by the points' x and y, the
widths, speeds and wire feeds, not by the height or the normals (it cuts the passes into
segments, `subdivide`, and carries those along). So a layer whose passes are those of a layer
levelled before in every field but these gets that layer's speeds and wire feeds on its own
passes cut the same way: the same passes, value for value, as levelling it again. Where the cut
does not give the points the earlier layer's levelled pass has, the layer is levelled anew
(nothing assumes more of what the feed-forward does to the points).

Pure: no I/O, no clocks.
"""
from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, Callable

import numpy as np

from planner.ahead import Later
from planner.feedforward import Envelope, FeedForwardOptions, LayerLevel, level_layer, subdivide
from planner.job import Pass

Levelled = tuple[tuple[Pass, ...], LayerLevel]
Submit = Callable[..., Later[Levelled]]


def _arr(h: hashlib.blake2b, a: np.ndarray | None) -> None:
    if a is None:
        h.update(b"-")
        return
    a = np.ascontiguousarray(a, dtype=np.float64)
    h.update(repr(a.shape).encode())
    h.update(a.tobytes())


def layer_key(passes: tuple[Pass, ...], *args: Any) -> bytes | None:
    """A digest of every input of `level_layer` but the points' height and the boundary normals
    (which it carries along and does not level by); None: not to be remembered."""
    h = hashlib.blake2b(repr(args).encode(), digest_size=32)
    for p in passes:
        h.update(repr((p.role, p.width_mm, p.current_a, p.speed_mm_min, p.wfs_m_min, p.inside_envelope)).encode())
        for a in (p.points[:, :2], p.axes, p.seg_speed_mm_min, p.seg_wfs_m_min):
            _arr(h, a)
    return h.digest()


class _Entry:
    """A layer levelled (or being levelled): its result, and which of its passes came back as they were sent."""

    def __init__(self, later: Later[Levelled], before: tuple[Pass, ...]) -> None:
        self._later: Later[Levelled] | None = later
        self._before: tuple[Pass, ...] | None = before
        self._value: tuple[tuple[Pass, ...], LayerLevel, tuple[bool, ...]] | None = None

    def result(self) -> Levelled:
        out, lvl, _ = self.taken()
        return out, lvl

    def taken(self) -> tuple[tuple[Pass, ...], LayerLevel, tuple[bool, ...]]:
        """(passes, level, kept): taken once (a Stealable runs its call again when asked twice)."""
        if self._value is None:
            assert self._later is not None and self._before is not None
            out, lvl = self._later.result()
            kept = tuple(k < len(self._before) and o is self._before[k] for k, o in enumerate(out))
            self._value, self._later, self._before = (out, lvl, kept), None, None
        return self._value


class Rebased:
    """A layer levelled before, given to a later layer of the same inputs (`passes`)."""

    def __init__(self, earlier: _Entry, passes: tuple[Pass, ...], fallback: Callable[[], Levelled]) -> None:
        self._earlier, self._passes, self._fallback = earlier, passes, fallback

    def result(self) -> Levelled:
        out, lvl, kept = self._earlier.taken()
        step = FeedForwardOptions().step_mm or max((p.width_mm for p in self._passes), default=1.0) / 2.0
        moved = []
        for k, o in enumerate(out):
            if kept[k]:   # came back as it was planned: this layer's own
                moved.append(self._passes[k])
                continue
            # levelled: this layer's pass cut as the feed-forward cuts it (its height, its normals
            # carried along), with the speeds and wire feeds levelled for the same inputs
            cut = subdivide(self._passes[k], step)
            if not np.array_equal(cut.points[:, :2], o.points[:, :2]):
                return self._fallback()
            moved.append(dataclasses.replace(o, points=cut.points, normals=cut.normals))
        return tuple(moved), lvl


class LevelMemo:
    """Layers levelled so far, by the digest of their inputs (`layer_key`); the results are the
    job's own passes, so keeping them costs no memory the job does not hold."""

    BOUND = 4096

    def __init__(self) -> None:
        self.seen: dict[bytes, _Entry] = {}
        self.hits = 0

    def level(self, submit: Submit, passes: tuple[Pass, ...], wire_diameter_mm: float,
              env: Envelope) -> Later[Levelled]:
        """`level_layer(passes, wire_diameter_mm, env)` through `submit` (a worker process or here),
        or a layer levelled before whose inputs were the same."""
        key = layer_key(passes, wire_diameter_mm, env)
        hit = self.seen.get(key) if key is not None else None
        if hit is not None:
            self.hits += 1
            return Rebased(hit, passes, lambda: level_layer(passes, wire_diameter_mm, env))
        entry = _Entry(submit(level_layer, passes, wire_diameter_mm, env), passes)
        if key is not None:
            if len(self.seen) >= self.BOUND:
                self.seen.clear()
            self.seen[key] = entry
        return entry

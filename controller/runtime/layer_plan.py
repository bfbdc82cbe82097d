"""Closed-loop layer height, the pure half (docs/closed-loop.md): the control law and the edits
it makes to the job's layers (planner.job `Layer`s, frozen: each edit is a copy). No I/O, no
clocks: unit-tested on typed layers.

Conventions (docs/process-physics.md): a layer's planned z (`z_mm`, every point's z) is the top
of the bead being laid; the contact tip sits the nominal stick-out L0 above it, so
CTWD = L0 + z − top, and a bead laid at z whose stick-out reads L has its top at z + L0 − L.

The law, after layer i with measured top T (mean over the layer's bead centre lines):
- gain: the measured tops against the model's cumulative rise E = Σ h·f(k) (k the speed factor
  each layer was laid with): ĝ the least-squares slope over the last `gain_window_layers`
  measured tops (and the substrate). f(k) = k^−p is the metal's effect on the rise, p = 1: an
  overlapped layer rises metal / step-over, a wall metal / the wall's width (set by the layers
  under it: a faster, narrower bead spreads on it, a slower, wider one first widens it);
- trim: the remaining layers must rise H − T (H the planned final top) where the model says
  ĝ·Σh·f(k): k = f⁻¹((H − T) / (ĝ·Σh)), kept inside [1 − trim, 1 + trim] and the cell's speed limit;
- layers: only when the trim cannot end within half a layer of H, one top layer per decision is
  added (a copy of the last two layers', one layer height up) or dropped;
- z: the next layer is laid at T + ĝ·f(k)·h (where its top will be): z offset = that − plan.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from planner.job import Layer

__all__ = ["Decision", "layer_z", "layer_height", "shift_layer", "trim_layer", "adjusted_layer",
           "extra_layer", "build_layers", "rise_factor", "speed_for", "fit_gain", "decide"]


def layer_z(layer: Layer) -> float:
    """The layer's planned top (its `z_mm`)."""
    return layer.z_mm


def layer_height(layer: Layer) -> float:
    return layer.height_mm


def shift_layer(layer: Layer, dz: float) -> Layer:
    """A copy of the layer with every point (and its z_mm) `dz` higher."""
    up = np.array([0.0, 0.0, dz])
    return replace(layer, z_mm=layer.z_mm + dz, passes=tuple(replace(p, points=p.points + up) for p in layer.passes),
                   extra=dict(layer.extra))


def trim_layer(layer: Layer, speed_factor: float) -> Layer:
    """A copy of the layer with every pass's travel speed (each segment's, cell-job/2) times `speed_factor`."""
    return replace(layer, passes=tuple(p.scaled(speed_factor) for p in layer.passes))


def adjusted_layer(layer: Layer, dz: float, speed_factor: float) -> Layer:
    """The layer as built: shifted by `dz`, its travel speeds trimmed by `speed_factor`."""
    out = shift_layer(layer, dz) if dz else layer
    return trim_layer(out, speed_factor) if speed_factor != 1.0 else out


def extra_layer(layers: Sequence[Layer], j: int) -> Layer:
    """Layer j ≥ len(layers): a copy of the last layer (or of the one before, so a wall keeps
    its alternating direction) one planned layer height above the previous top (`extra["added"]`)."""
    n = len(layers)
    if j < n:
        raise ValueError(f"layer {j} is a planned layer, not an extra one")
    last = layers[-1]
    template = layers[n - 2 + (j - n) % 2] if n >= 2 else last
    h = layer_height(last) or (layer_z(last) - layer_z(layers[-2]) if n >= 2 else 1.0)
    z = layer_z(last) + h * (j - n + 1)
    out = shift_layer(template, z - layer_z(template))
    return replace(out, index=j, z_mm=z, height_mm=h, extra={**template.extra, "added": True})


def build_layers(layers: Sequence[Layer], n_total: int) -> list[Layer]:
    """The layers a build lays: the planned ones, the first `n_total` of them or extra ones after."""
    if n_total <= len(layers):
        return list(layers[:n_total])
    return list(layers) + [extra_layer(layers, j) for j in range(len(layers), n_total)]


def rise_factor(speed_factor: float, p: float) -> float:
    return float(speed_factor ** (-p))


def speed_for(f: float, p: float) -> float:
    """The speed factor whose rise factor is `f` (inverse of rise_factor)."""
    return float(f ** (-1.0 / p))


def fit_gain(points: list[tuple[float, float]], window: int, lo: float = 0.3, hi: float = 2.0) -> float | None:
    """ĝ: the slope of the measured top against the model's cumulative rise over the last `window`
    points (least squares; a top's noise does not add up the way layer-to-layer differences do).
    None below two points or without spread; clipped to [lo, hi]."""
    pts = points[-max(window, 2):]
    if len(pts) < 2:
        return None
    n = len(pts)
    mx = sum(e for e, _ in pts) / n
    my = sum(t for _, t in pts) / n
    sxx = sum((e - mx) ** 2 for e, _ in pts)
    if sxx <= 1e-9:
        return None
    g = sum((e - mx) * (t - my) for e, t in pts) / sxx
    return min(max(g, lo), hi) if math.isfinite(g) else None


@dataclass(frozen=True)
class Decision:
    n_total: int            # layers to build in all (planned ± added / dropped)
    speed_factor: float     # travel speed of the remaining layers / the plan's
    projected_top_mm: float  # where the model says the build ends
    action: str             # "none" | "trim" | "add N" | "drop N" (+ ", trim")


def _clip_k(k: float, lo: float, hi: float) -> float:
    return min(max(k, lo), hi)


def decide(*, top_mm: float, final_mm: float, heights: list[float], gain: float, p: float,
           k_range: tuple[float, float], n_done: int, n_total: int, n_planned: int,
           layer_change: bool = True, tol_mm: float = 0.25, margin_mm: float = 0.1,
           n_range: tuple[int, int] = (0, 1 << 30)) -> Decision:
    """The trim (and the layer count) that end the build at `final_mm` from `top_mm`.

    `heights`: the planned height of every layer of the current plan (len n_total) and after
    (the extra layers' height is the last one's); `n_done` layers are built; the layer count
    stays inside `n_range`.
    """
    lo, hi = k_range
    h_extra = heights[n_planned - 1] if n_planned else (heights[-1] if heights else 0.0)

    def outcome(n: int) -> tuple[float, float]:
        hs = [heights[j] if j < n_planned else h_extra for j in range(n_done, n)]
        s = sum(hs)
        need = final_mm - top_mm
        if s <= 0.0 or gain <= 0.0:
            return 1.0, top_mm
        f = need / (gain * s)
        k = _clip_k(speed_for(f, p), lo, hi) if f > 0 else hi
        return k, top_mm + gain * s * rise_factor(k, p)

    k, proj = outcome(n_total)
    n = n_total
    layer_rise = gain * h_extra
    miss = abs(proj - final_mm)
    if layer_change and miss > min(0.5 * layer_rise, tol_mm):
        # the trim cannot end near the plan: one layer more (or less) a decision, when it ends nearer
        # (by half a layer when the trim misses by more than that, else by `margin_mm`)
        cand = n_total + (1 if proj < final_mm else -1)
        if max(n_done, n_range[0]) <= cand <= n_range[1]:
            kc, pc = outcome(cand)
            gain_mm = miss - abs(pc - final_mm)
            if gain_mm > (0.0 if miss > 0.5 * layer_rise else margin_mm):
                n, k, proj = cand, kc, pc
    action = []
    if n > n_total:
        action.append(f"add {n - n_total}")
    elif n < n_total:
        action.append(f"drop {n_total - n}")
    if abs(k - 1.0) > 1e-6:
        action.append("trim")
    return Decision(n, k, proj, ", ".join(action) or "none")

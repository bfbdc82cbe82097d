"""Probing a surface from above at CAD-frame spots: the repair's stock probe and its verify.

`repaired_spots` picks the verify's spots: a grid over the repaired region (where the stock lies
below the CAD top by more than 0.05 mm), kept `inset_mm` in from its boundary, spread by
farthest-point sampling. `stock_spots` picks the stock probe's, dense where a deposit falls short
(docs/machining.md "The stock probe"): the region's corners, a ring along its boundary, then a
grid over its inside. `probe_cad_points` touches them through the alignment transform
(CAD → machine) and reads the touches back into the CAD frame.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from controller.align.probe_cycle import ProbeTarget, probe_points
from controller.ports import ProbePort
from core.config import CellConfig, ProbeSettings
from core.errors import InputError
from planner.finish import cad_top

F = NDArray[np.float64]


def spread(cand: F, n: int, first_farthest: bool = False) -> F:
    """n of the candidates by farthest-point sampling; the first the one nearest their centre (or,
    with `first_farthest`, farthest from it)."""
    if len(cand) <= n:
        return cand
    r = np.linalg.norm(cand - cand.mean(axis=0), axis=1)
    pick = [int(np.argmax(r) if first_farthest else np.argmin(r))]
    d = np.linalg.norm(cand - cand[pick[0]], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(d))
        pick.append(k)
        d = np.minimum(d, np.linalg.norm(cand - cand[k], axis=1))
    return cand[pick]


def repaired_spots(cad_tri: F, stock_tri: F, bounds_xy: F, n: int, inset_mm: float = 1.5,
                   step_mm: float = 0.5) -> F:
    """Up to n xy spots (CAD frame) on the repaired region, `inset_mm` inside its boundary."""
    # lazy: scipy's ndimage loads only when this path runs (start-up time)
    from scipy.ndimage import binary_erosion

    xy, mask, _shape = _repaired_mask(cad_tri, stock_tri, bounds_xy, step_mm)
    r = int(np.ceil(inset_mm / step_mm))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    core = binary_erosion(mask, structure=(xx * xx + yy * yy) <= r * r, border_value=0)
    if not core.any():
        core = mask
    if not core.any():
        raise InputError("repair: no repaired region to probe (the stock meets the CAD everywhere in the bounds)")
    return spread(xy[core.ravel()], n)


def _repaired_mask(cad_tri: F, stock_tri: F, bounds_xy: F, step_mm: float) -> tuple[F, np.ndarray, tuple[int, int]]:
    """Cell centres over the bounds (step_mm), and where the stock lies > 0.05 mm below the CAD top."""
    lo, hi = np.asarray(bounds_xy, dtype=float)[0, :2], np.asarray(bounds_xy, dtype=float)[1, :2]
    xs = np.arange(lo[0] + step_mm / 2, hi[0], step_mm)
    ys = np.arange(lo[1] + step_mm / 2, hi[1], step_mm)
    gx, gy = np.meshgrid(xs, ys)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    missing = cad_top(cad_tri, xy) - np.nan_to_num(cad_top(stock_tri, xy), neginf=-1e9)
    return xy, (np.isfinite(missing) & (missing > 0.05)).reshape(gx.shape), gx.shape


def _spaced(xy: F, order: np.ndarray, spacing: float, fixed: F | None = None) -> list[int]:
    """Indices taken in `order`, each at least `spacing` from every one taken before (and from `fixed`)."""
    taken: list[int] = []
    near = np.empty((0, 2)) if fixed is None else np.asarray(fixed, dtype=float).reshape(-1, 2)
    for i in order:
        if not len(near) or float(np.min(np.hypot(*(near - xy[i]).T))) >= spacing - 1e-9:
            taken.append(int(i))
            near = np.vstack([near, xy[i]])
    return taken


def stock_spots(cad_tri: F, stock_tri: F, bounds_xy: F, *, ring_step_mm: float = 0.5, inner_step_mm: float = 2.0,
                ring_inset_mm: float = 0.25, step_mm: float = 0.5) -> tuple[F, list[str]]:
    """The stock probe's spots (CAD frame) and their kinds ("corner", "ring", "inside").

    A deposit falls short first where its beads end: the repaired region's corners and along its
    boundary. Ring: the cells about `ring_inset_mm` in from the boundary, taken most-enclosed first
    (the count of outside cells within 2 mm: corners come first), `ring_step_mm` apart; inside: the
    cells deeper than twice that, deepest first, `inner_step_mm` from every spot taken."""
    # lazy: scipy's ndimage loads only when this path runs (start-up time)
    from scipy.ndimage import convolve, distance_transform_edt

    xy, mask, shape = _repaired_mask(cad_tri, stock_tri, bounds_xy, step_mm)
    if not mask.any():
        raise InputError("repair: no repaired region to probe (the stock meets the CAD everywhere in the bounds)")
    depth = distance_transform_edt(np.pad(mask, 1)).astype(float)[1:-1, 1:-1] * step_mm   # to the nearest outside
    r = int(np.ceil(2.0 / step_mm))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    outside = convolve((~mask).astype(float), ((xx * xx + yy * yy) <= r * r).astype(float), mode="constant", cval=1.0)
    d, o = depth.ravel(), outside.ravel()
    ring = np.flatnonzero(mask.ravel() & (np.abs(d - ring_inset_mm - step_mm / 2) <= step_mm / 2 + 1e-9))
    ring = ring[np.argsort(-o[ring], kind="stable")]
    pick = _spaced(xy, ring, ring_step_mm)
    corner = max(float(np.median(o[ring])) * 1.3, 1.0) if len(ring) else np.inf
    inner = np.flatnonzero(mask.ravel() & (d >= 2 * ring_inset_mm + step_mm))
    inner = inner[np.argsort(-d[inner], kind="stable")]
    pick_inner = _spaced(xy, inner, inner_step_mm, xy[pick])
    if not pick and not pick_inner:   # a sliver: its middle
        pick_inner = [int(np.flatnonzero(mask.ravel())[np.argmax(d[mask.ravel()])])]
    kinds = ["corner" if o[i] >= corner else "ring" for i in pick] + ["inside"] * len(pick_inner)
    return xy[pick + pick_inner], kinds


def _touches_and_cells(cad_tri: F, stock_tri: F, bounds_xy: F, touched: F, low: np.ndarray,
                       step_mm: float) -> tuple[F, F, F]:
    """The touched spots (n, 2), the low ones among them, and the repaired region's cells (none
    computed when no touch is low)."""
    t = np.asarray(touched, dtype=float).reshape(-1, 2)
    lows = t[np.asarray(low, dtype=bool)]
    if not len(lows):
        return t, lows, np.empty((0, 2))
    xy, mask, _shape = _repaired_mask(cad_tri, stock_tri, bounds_xy, step_mm)
    cells: F = xy[mask.ravel()]
    return t, lows, cells


def refine_spots(cad_tri: F, stock_tri: F, bounds_xy: F, touched: F, low: np.ndarray, spacing_mm: float,
                 step_mm: float = 0.5) -> F:
    """More spots around the `low` touches (docs/machining.md "The stock probe"): cells of the
    repaired region within twice `spacing_mm` of a low touch, nearest first, each `spacing_mm` from
    every touch and from each other. A deposit short at a touch is short around it (a corner the
    beads turned short of, a valley between beads), and a depositing again there fills only where
    it lands: its neighbours are touched too, before the spots are judged."""
    from scipy.spatial import cKDTree   # lazy: scipy loads only when this path runs (start-up time)

    t, lows, cells = _touches_and_cells(cad_tri, stock_tri, bounds_xy, touched, low, step_mm)
    if not len(lows):
        return np.empty((0, 2))
    d = cKDTree(lows).query(cells)[0]
    near = np.flatnonzero(d <= 2 * spacing_mm + 1e-9)
    order = near[np.argsort(d[near], kind="stable")]
    out: F = cells[_spaced(cells, order, spacing_mm, t)]
    return out


SCAN_CLEARANCE_MM = 3.0   # the stock scan starts this far over the highest top it expects
SCAN_BACKOFF_MM = 0.5     # and backs off this far for its one slow touch


def scan_settings(s: ProbeSettings) -> ProbeSettings:
    """The stock probe's touch (docs/machining.md "The stock probe"): hundreds of spots judged against
    `min_stock_mm`, so one slow touch (the probe's noise is µm, the judgement's band 0.1 mm), a
    short back-off, and a low hop between spots; the alignment and the verify keep the full cycle."""
    return s.model_copy(update={"samples": 1, "retries": 0, "backoff_mm": min(float(s.backoff_mm), SCAN_BACKOFF_MM),
                                "clearance_mm": min(float(s.clearance_mm), SCAN_CLEARANCE_MM)})


async def probe_cad_points(link: ProbePort, cell: CellConfig, xy: F, top_z: float, transform: F,
                           name: str = "stock", settings: ProbeSettings | None = None) -> F:
    """Touch each CAD-frame spot from above (starting `clearance` over `top_z`, the highest the
    surface may stand under any spot, hops between spots `clearance` over the highest start);
    (n, 3) CAD frame. `settings`: the touch cycle (default cell.yaml's `probe`)."""
    s = settings if settings is not None else cell.probe
    clear = float(s.clearance_mm)
    tf = np.asarray(transform, dtype=float)
    down = tf[:3, :3] @ np.array([0.0, 0.0, -1.0])
    starts = [tf[:3, :3] @ np.array([x, y, top_z + clear]) + tf[:3, 3] for x, y in xy]
    safe = max(s[2] for s in starts) + clear
    dn = (float(down[0]), float(down[1]), float(down[2]))
    targets = [ProbeTarget(f"{name}[{i}]", (float(s[0]), float(s[1]), float(s[2])), dn, float(safe))
               for i, s in enumerate(starts)]
    got = await probe_points(link, targets, s)
    await link.command(f"G90 G0 Z{safe:.3f}")
    inv = np.linalg.inv(tf)
    out: F = np.array([inv[:3, :3] @ p.position + inv[:3, 3] for p in got])
    return out


def flood_spots(cad_tri: F, stock_tri: F, bounds_xy: F, touched: F, low: np.ndarray, reach_mm: float = 0.75,
                step_mm: float = 0.5) -> F:
    """Every cell of the repaired region within `reach_mm` of a `low` touch (its neighbours, the
    diagonal ones too) that no touch has read yet (docs/machining.md "The stock probe"): touched,
    and around the low ones of those again, it traces a low stretch of the deposit cell by cell
    out to where it stands clear of the need."""
    from scipy.spatial import cKDTree   # lazy: scipy loads only when this path runs (start-up time)

    t, lows, cells = _touches_and_cells(cad_tri, stock_tri, bounds_xy, touched, low, step_mm)
    if not len(lows):
        return np.empty((0, 2))
    near = cKDTree(lows).query(cells)[0] <= reach_mm + 1e-9
    fresh = cKDTree(t).query(cells)[0] > step_mm / 2
    out: F = cells[near & fresh]
    return out

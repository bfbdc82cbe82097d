"""Probing a surface from above at CAD-frame spots: the repair's stock probe and its verify.

`repaired_spots` picks the spots: a grid over the repaired region (where the stock lies below
the CAD top by more than 0.05 mm), kept `inset_mm` in from its boundary, spread by farthest-point
sampling. `probe_cad_points` touches them through the alignment transform (CAD → machine) and
reads the touches back into the CAD frame.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from controller.align.probe_cycle import ProbeTarget, probe_points
from controller.ports import ProbePort
from core.errors import InputError
from planner.finish import cad_top

F = NDArray[np.float64]


def _spread(cand: F, n: int) -> F:
    """n of the candidates by farthest-point sampling, the first nearest their centre."""
    if len(cand) <= n:
        return cand
    pick = [int(np.argmin(np.linalg.norm(cand - cand.mean(axis=0), axis=1)))]
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

    lo, hi = np.asarray(bounds_xy, dtype=float)[0, :2], np.asarray(bounds_xy, dtype=float)[1, :2]
    xs = np.arange(lo[0] + step_mm / 2, hi[0], step_mm)
    ys = np.arange(lo[1] + step_mm / 2, hi[1], step_mm)
    gx, gy = np.meshgrid(xs, ys)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    missing = cad_top(cad_tri, xy) - np.nan_to_num(cad_top(stock_tri, xy), neginf=-1e9)
    mask = (np.isfinite(missing) & (missing > 0.05)).reshape(gx.shape)
    r = int(np.ceil(inset_mm / step_mm))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    core = binary_erosion(mask, structure=(xx * xx + yy * yy) <= r * r, border_value=0)
    if not core.any():
        core = mask
    if not core.any():
        raise InputError("repair: no repaired region to probe (the stock meets the CAD everywhere in the bounds)")
    return _spread(xy[core.ravel()], n)


async def probe_cad_points(link: ProbePort, cell: Any, xy: F, top_z: float, transform: F,
                           name: str = "stock") -> F:
    """Touch each CAD-frame spot from above (starting `clearance` over `top_z`); (n, 3) CAD frame."""
    clear = float(cell.probe.clearance_mm)
    tf = np.asarray(transform, dtype=float)
    down = tf[:3, :3] @ np.array([0.0, 0.0, -1.0])
    starts = [tf[:3, :3] @ np.array([x, y, top_z + clear]) + tf[:3, 3] for x, y in xy]
    safe = max(s[2] for s in starts) + clear
    dn = (float(down[0]), float(down[1]), float(down[2]))
    targets = [ProbeTarget(f"{name}[{i}]", (float(s[0]), float(s[1]), float(s[2])), dn, float(safe))
               for i, s in enumerate(starts)]
    got = await probe_points(link, targets, cell.probe)
    await link.command(f"G90 G0 Z{safe:.3f}")
    inv = np.linalg.inv(tf)
    out: F = np.array([inv[:3, :3] @ p.position + inv[:3, 3] for p in got])
    return out

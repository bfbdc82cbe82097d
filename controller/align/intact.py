"""The alignment's touches of a repair, chosen on the intact faces off the repair region (pure).

A repair region anywhere on the top face can be aligned (docs/repair.md "Alignment spots"):
- top: the CAD's top face (its highest horizontal facets) where the CAD stands at full height,
  `edge_mm` in from the face's edges and `keep_out_mm` away from the repair region's xy bounds,
  sampled on a 1 mm grid; `n` spots spread over it by farthest-point sampling (the first the one
  farthest from the centre, so the plane fit gets the widest base);
- side (+X face) and third face (−Y): touched where the region (with its keep-out) does not reach
  that face, on the longest free stretch;
- refused (InputError) only when too little is left: the intact top's extent along its narrower
  direction under `min_span_mm`, or a face's free stretch under `min_side_mm`; the message says how
  much is left and where it looked.

The keep-out covers the pose the alignment has not measured yet: the first touches go to nominal
CAD positions on a part that may sit up to `POSE_OFFSET_MM` off and `POSE_ROTATION_DEG` turned about
the table's origin, so a spot r mm from the origin may land `POSE_OFFSET_MM + CLEAR_MM + r·sin(rotation)`
from where it was aimed: that far from the region and from the top face's edges (8 directions).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core.errors import InputError
from controller.align.surface_probe import spread
from planner.finish import cad_top

F = NDArray[np.float64]
POSE_OFFSET_MM = 5.0     # the part's offset on the table the first touches must tolerate
POSE_ROTATION_DEG = 5.0  # ... and its rotation about the table's origin
CLEAR_MM = 1.0           # beyond that, between a touch and an edge or the region
MIN_SPAN_MM = 8.0     # the intact top's narrower extent the plane fit needs
MIN_SIDE_MM = 4.0     # a face's free stretch the side / third touches need
FACE_CLEAR_MM = 2.0   # a region whose bottom stays this far above the side touches leaves the faces intact


@dataclass(frozen=True)
class Spots:
    top_xy: F                      # (n, 2) on the intact top, CAD frame
    side_y: tuple[float, float]    # the +X face's free stretch (y from, to) for its row of touches
    tertiary_x: float              # where the −Y face is touched
    intact_mm2: float              # the intact top area the spots were chosen on
    span_mm: tuple[float, float]   # its extent along its principal directions (wide, narrow)


def _extent(pts: F) -> tuple[float, float]:
    """The points' extent along their principal directions (wide, narrow)."""
    if len(pts) < 2:
        return 0.0, 0.0
    c = pts - pts.mean(axis=0)
    _, vec = np.linalg.eigh(c.T @ c)
    proj = c @ vec
    ext = proj.max(axis=0) - proj.min(axis=0)
    return float(ext.max()), float(ext.min())


def _free_stretch(lo: float, hi: float, block: tuple[float, float] | None) -> tuple[float, float]:
    """The longest part of [lo, hi] outside `block` (None: nothing blocked)."""
    if block is None or block[1] <= lo or block[0] >= hi:
        return lo, hi
    parts = [(lo, min(hi, block[0])), (max(lo, block[1]), hi)]
    return max(parts, key=lambda p: p[1] - p[0])


def keep_out_mm(xy: F) -> F:
    """How far from an edge or the region a spot must be aimed (mm): the unmeasured pose's reach there."""
    r = np.hypot(xy[:, 0], xy[:, 1])
    out: F = POSE_OFFSET_MM + CLEAR_MM + r * np.sin(np.radians(POSE_ROTATION_DEG))
    return out


def _box_distance(xy: F, lo: F, hi: F) -> F:
    """Each point's distance to the box [lo, hi] (0 inside)."""
    d = np.maximum(np.maximum(lo - xy, xy - hi), 0.0)
    out: F = np.hypot(d[:, 0], d[:, 1])
    return out


def intact_spots(cad_tri: F, region: F, n: int = 9, *, face_z: float | None = None, min_span_mm: float = MIN_SPAN_MM,
                 min_side_mm: float = MIN_SIDE_MM, step_mm: float = 1.0) -> Spots:
    """The touches for a part whose repair region has the bounds `region` ((2, 2|3): lo, hi); the
    side faces are touched at `face_z` (None: as deep as the part), a region whose bottom stays
    `FACE_CLEAR_MM` above it does not reach them."""
    tri = np.asarray(cad_tri, dtype=float).reshape(-1, 3, 3)
    lo, hi = tri.reshape(-1, 3).min(axis=0), tri.reshape(-1, 3).max(axis=0)
    r = np.asarray(region, dtype=float)
    xs = np.arange(lo[0] + POSE_OFFSET_MM, hi[0] - POSE_OFFSET_MM + 1e-9, step_mm)
    ys = np.arange(lo[1] + POSE_OFFSET_MM, hi[1] - POSE_OFFSET_MM + 1e-9, step_mm)
    gx, gy = np.meshgrid(xs, ys)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    u = keep_out_mm(xy)
    full = _box_distance(xy, r[0, :2], r[1, :2]) >= u        # off the region by the pose's reach
    if full.any():   # the full-height top all around, as far as the pose reaches
        ang = np.radians(np.arange(0, 360, 45))
        ring = np.column_stack([np.cos(ang), np.sin(ang)])
        idx = np.flatnonzero(full)
        pts = np.vstack([xy[idx], (xy[idx][:, None, :] + u[idx][:, None, None] * ring[None]).reshape(-1, 2)])
        ok = cad_top(tri, pts) >= hi[2] - 1e-3
        full[idx] = ok[:len(idx)] & ok[len(idx):].reshape(-1, len(ring)).all(axis=1)
    cand = xy[full]
    area = float(len(cand) * step_mm * step_mm)
    wide, narrow = _extent(cand)
    where = (f"the top face {hi[0] - lo[0]:.1f} × {hi[1] - lo[1]:.1f} mm less the repair region x "
             f"{r[0, 0]:.1f}…{r[1, 0]:.1f}, y {r[0, 1]:.1f}…{r[1, 1]:.1f} mm, each touch {POSE_OFFSET_MM + CLEAR_MM:g} mm "
             f"+ {POSE_ROTATION_DEG:g}° of its radius clear of the region and the edges (the pose not yet measured)")
    if len(cand) < 3 or narrow < min_span_mm:
        raise InputError(f"repair: too little intact top face is left for the alignment's touches: {area:.0f} mm² "
                         f"spanning {wide:.1f} × {narrow:.1f} mm on {where}; the plane fit needs at least "
                         f"{min_span_mm:g} mm across (a smaller repair region, or align the part with `cell align run` "
                         "on another face)")
    # the side faces: the region's keep-out at that face (its corner farthest from the origin)
    far = np.array([[r[1, 0], r[0, 1]], [r[1, 0], r[1, 1]], [r[0, 0], r[0, 1]]])
    k = keep_out_mm(far)
    edge = POSE_OFFSET_MM + CLEAR_MM + float(np.hypot(hi[0], hi[1])) * np.sin(np.radians(POSE_ROTATION_DEG))
    shallow = face_z is not None and r.shape[1] > 2 and r[0, 2] >= face_z + FACE_CLEAR_MM
    reach_x = not shallow and r[1, 0] + k[:2].max() >= hi[0]     # the region's keep-out reaches the +X face
    kx = float(k[:2].max())
    sy = _free_stretch(lo[1] + edge, hi[1] - edge, (r[0, 1] - kx, r[1, 1] + kx) if reach_x else None)
    ky = float(k[[0, 2]].max())
    reach_y = not shallow and r[0, 1] - ky <= lo[1]              # ... or the −Y face
    sx = _free_stretch(lo[0] + edge, hi[0] - edge, (r[0, 0] - ky, r[1, 0] + ky) if reach_y else None)
    for name, (a, b) in (("+X", sy), ("−Y", sx)):
        if b - a < min_side_mm:
            raise InputError(f"repair: too little intact {name} face is left for the alignment's side touches: "
                             f"{max(b - a, 0.0):.1f} mm free beside the repair region and the corners (each touch "
                             f"{POSE_OFFSET_MM + CLEAR_MM:g} mm + {POSE_ROTATION_DEG:g}° of its radius clear of them); "
                             f"it needs {min_side_mm:g} mm")
    return Spots(spread(cand, n, first_farthest=True), (float(sy[0]), float(sy[1])), float((sx[0] + sx[1]) / 2), area, (wide, narrow))

"""5-axis deposition (Kerschbaumer 2004): tool axis per point, the overhang rule, nozzle collisions.

Pure: a planned Job in, a Job (with `axes` per pass) or findings out. Choices (docs/kinematics.md,
docs/planner.md "5-axis"):

* Tool axis = the local build direction, so the table turns it vertical (down-hand): where the
  next layer lies over this one. The layer moves like its centroid (the shift s of the sliced
  region's centroid over one layer height, per mm of height) and, at a boundary bead (perimeter or
  lone bead) with a usable facet normal n and bead tangent t, its outline steps out along the
  wall: the steepest ascent g = ``n × t`` (oriented up) gives the step across the bead, s·t the
  slide along it, so the axis is ``g / g_z + (s·t) t``. A tilted tube's wall gets the tube's axis
  at every point of the ring (the steepest ascent alone is vertical on its flanks), a frustum's
  wall its slope. Elsewhere (infill, near-horizontal facets) the axis is the centroid's shift.
* Smoothed along the bead (moving average over ± `smooth_mm` of arc length, wrapping on closed
  beads), then held within `tilt_limit_deg` of the part's vertical.
* Overhang rule, at the perimeter beads: the step out Δx is how much farther out the layer's outline
  lies than the outline of the layer below, read one layer down along the tool axis; it breaks
  the rule when
  ``Δx > min(w/2, Δz·tan(max_overhang_deg))`` (+10 µm): the melt-pool limit of the paper and its
  measured 30° for 3-axis walls.
* Nozzle: a cone with its tip `standoff_mm` along the tool axis above the point, opening upward
  by `half_angle_deg` over `length_mm`; a built bead point inside it (with half a bead height of
  margin) is a collision.
"""
from __future__ import annotations

import dataclasses
from typing import Any
from dataclasses import dataclass

import numpy as np
import shapely

from core.errors import CellError
from planner.job import Job, Layer, Pass

Z = np.array([0.0, 0.0, 1.0])
_TOL_MM = 0.01


class CollisionError(CellError):
    """The nozzle would hit the part built so far."""


class OverhangError(CellError):
    """A layer steps out beyond the overhang rule on the chosen path."""


@dataclass(frozen=True)
class Nozzle:
    half_angle_deg: float = 15.0
    length_mm: float = 60.0
    standoff_mm: float = 3.0


@dataclass(frozen=True)
class FiveAxisOptions:
    tilt_limit_deg: float = 60.0
    smooth_mm: float | None = None         # default: one bead width
    max_overhang_deg: float = 30.0         # the paper: 3-axis walls overhang up to 30°
    nozzle: Nozzle | None = Nozzle()


# --- tool axes ------------------------------------------------------------------------------------

def _unit_rows(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.where(n > 1e-12, v / np.where(n > 1e-12, n, 1.0), Z)


def _closed(pts: np.ndarray) -> bool:
    return len(pts) > 3 and float(np.linalg.norm(pts[0] - pts[-1])) < 1e-6


def _tangents(pts: np.ndarray) -> np.ndarray:
    if _closed(pts):
        nxt, prv = np.roll(pts, -1, axis=0), np.roll(pts, 1, axis=0)
        nxt[-1], prv[0] = pts[1], pts[-2]
        return _unit_rows(nxt - prv)
    return _unit_rows(np.gradient(pts, axis=0))


def _centroid(layer: Layer, region: shapely.Geometry | None = None) -> np.ndarray | None:
    """The layer's centroid: its sliced region's (area), else its beads' (length-weighted)."""
    if region is not None and not region.is_empty and region.area > 0:
        c = region.centroid
        return np.array([c.x, c.y, layer.z_mm])
    acc, total = np.zeros(3), 0.0
    for p in layer.passes:
        seg = np.linalg.norm(np.diff(p.points, axis=0), axis=1)
        mid = 0.5 * (p.points[1:] + p.points[:-1])
        acc += (mid * seg[:, None]).sum(axis=0)
        total += float(seg.sum())
    return acc / total if total > 0 else None


def _layer_directions(job: Job, regions: list[shapely.Geometry] | None = None
                      ) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """Build direction per layer from the shift of the layer centroid over one layer height (the
    first layer takes the second's), and the layer's centroid."""
    out: list[tuple[np.ndarray, np.ndarray | None]] = []
    prev = None
    for k, layer in enumerate(job.layers):
        c = _centroid(layer, regions[k] if regions is not None and k < len(regions) else None)
        d = Z.copy()
        if c is not None and prev is not None and c[2] - prev[2] > 1e-9:
            d = (c - prev) / np.linalg.norm(c - prev)
        out.append((d, c))
        prev = c if c is not None else prev
    if len(out) > 1:  # the first layer has none below: it grows where the second one does
        out[0] = (out[1][0], out[0][1])
    return out


def _slide(across: np.ndarray, t: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The layer's slide along the bead per mm of height, (u·t)·t, with u = s + κ·r.

    The sections of a cone by parallel planes are homothetic about its apex: the layer above is
    this one shifted (s, the centroid's shift) and scaled about its centroid (κ per mm, r = the
    point's offset from the centroid). The step across the bead (`across`, from the facets) is
    u's component across it; κ is fitted to it (least squares over the bead), and u's component
    along the bead is the slide (an ellipse scaled about its centre slides along itself)."""
    nu = np.column_stack([t[:, 1], -t[:, 0]])
    rn = (r * nu).sum(axis=1)
    den = float((rn * rn).sum())
    kappa = float((rn * ((across[:, :2] - s[:2]) * nu).sum(axis=1)).sum()) / den if den > 1e-9 else 0.0
    u = s[:2] + kappa * r
    out: np.ndarray = (u * t[:, :2]).sum(axis=1)[:, None] * t
    return out


def _raw_axes(p: Pass, layer_dir: np.ndarray, centre: np.ndarray | None = None) -> np.ndarray:
    """Where the next layer lies over each point: the wall's step across the bead (its steepest
    ascent) plus the layer's slide along it (the centroid's shift); see the module docstring."""
    ax = np.tile(layer_dir, (len(p.points), 1))
    if p.normals is None:  # boundary beads (perimeters, lone beads of a single-bead wall) carry normals
        return ax
    n = _unit_rows(np.asarray(p.normals, dtype=float))
    t = _tangents(p.points)
    g = np.cross(n, t)
    g = np.where(g[:, 2:3] < 0, -g, g)
    ok = (np.abs(n[:, 2]) < 0.95) & (np.linalg.norm(g, axis=1) > 0.5)
    if not ok.any():
        return ax
    shift = layer_dir / max(float(layer_dir[2]), 1e-6)   # the centroid's shift per mm of height
    across = g[ok] / np.maximum(g[ok, 2:3], 1e-6)         # the wall's step across the bead, per mm
    r = p.points[ok, :2] - (centre[:2] if centre is not None else p.points[:, :2].mean(axis=0))
    ax[ok] = _unit_rows(across + _slide(across, t[ok], r, shift))
    return ax


def smooth(points: np.ndarray, axes: np.ndarray, window_mm: float) -> np.ndarray:
    """Moving average of unit axes over ± window_mm of arc length (wrapping on closed beads)."""
    n = len(points)
    if n < 3 or window_mm <= 0:
        return _unit_rows(axes)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    # each point stands for half of its two segments: an arc-length average, not a point count
    wt = np.concatenate([[0.0], seg]) / 2 + np.concatenate([seg, [0.0]]) / 2
    if _closed(points):  # the last point repeats the first: average over the ring
        L = s[-1]
        wt = wt[:-1].copy()
        wt[0] += seg[-1] / 2
        s3 = np.concatenate([s[:-1] - L, s[:-1], s[:-1] + L])
        a3 = np.concatenate([axes[:-1]] * 3)
        w3 = np.concatenate([wt] * 3)
    else:
        s3, a3, w3 = s, axes, wt
    w3 = np.maximum(w3, 1e-9)
    cs = np.vstack([np.zeros(3), np.cumsum(a3 * w3[:, None], axis=0)])
    lo = np.searchsorted(s3, s - window_mm, side="left")
    hi = np.searchsorted(s3, s + window_mm, side="right")
    return _unit_rows(cs[hi] - cs[lo])


def clamp_tilt(axes: np.ndarray, limit_deg: float) -> np.ndarray:
    """Axes tilted more than limit_deg from +Z turned back toward +Z onto the limit."""
    axes = _unit_rows(axes)
    tilt = np.arccos(np.clip(axes[:, 2], -1.0, 1.0))
    lim = np.radians(limit_deg)
    over = tilt > lim
    if not over.any():
        return axes
    h = axes[over, :2]
    hn = np.linalg.norm(h, axis=1, keepdims=True)
    h = np.where(hn > 1e-12, h / np.where(hn > 1e-12, hn, 1.0), [1.0, 0.0])
    out = axes.copy()
    out[over] = np.column_stack([h * np.sin(lim), np.full(len(h), np.cos(lim))])
    return out


def tool_axes(job: Job, opt: FiveAxisOptions, regions: list[shapely.Geometry] | None = None) -> Job:
    """The job with `axes` on every pass: local build direction, smoothed, within the tilt limit.

    `regions`: each layer's sliced outline (the centroids' shift), else the layer's beads."""
    dirs = _layer_directions(job, regions)
    window = opt.smooth_mm if opt.smooth_mm is not None else job.bead.width_mm
    layers = []
    for layer, (d, c) in zip(job.layers, dirs):
        passes = []
        for p in layer.passes:
            ax = clamp_tilt(smooth(p.points, _raw_axes(p, d, c), window), opt.tilt_limit_deg)
            passes.append(dataclasses.replace(p, axes=np.round(ax, 5)))
        layers.append(dataclasses.replace(layer, passes=tuple(passes)))
    return dataclasses.replace(job, layers=tuple(layers))


# --- the overhang rule -----------------------------------------------------------------------------

def _material(layer: Layer) -> shapely.Geometry:
    """The layer's outline from its beads (when the slice regions are not at hand)."""
    beads = [shapely.LineString(p.points[:, :2]).buffer(p.width_mm / 2.0) for p in layer.passes
             if len(p.points) >= 2]
    return shapely.union_all(beads) if beads else shapely.Polygon()


def _signed(region: shapely.Geometry, xy: np.ndarray) -> np.ndarray:
    """Signed distance of points to a region's outline: negative inside."""
    d = shapely.distance(region.boundary, shapely.points(xy))
    return np.asarray(np.where(shapely.contains_xy(region, xy[:, 0], xy[:, 1]), -d, d))


def overhangs(job: Job, max_overhang_deg: float = 30.0,
              regions: list[shapely.Geometry] | None = None) -> list[dict[str, Any]]:
    """Layers whose outline steps out beyond the rule on the job's path (its `axes`, vertical if absent).

    The step out at a perimeter point p is how much farther out the layer's outline lies than the
    outline of the layer below, one layer down along p's tool axis: sd_below(foot) − sd_this(p).
    """
    regions = regions if regions is not None else [_material(L) for L in job.layers]
    out = []
    for k in range(1, len(job.layers)):
        below, layer = job.layers[k - 1], job.layers[k]
        rb, rl = regions[k - 1], regions[k]
        if rb.is_empty or rl.is_empty or not layer.passes:
            continue
        dz = float(layer.z_mm - below.z_mm)
        w = max(p.width_mm for p in layer.passes)
        limit = min(w / 2.0, dz * np.tan(np.radians(max_overhang_deg)))
        worst: float = 0.0
        where: np.ndarray | None = None
        for p in layer.passes:
            if p.role != "perimeter" and p.normals is None:  # the boundary steps out (loops, lone beads)
                continue
            ax = p.axes if p.axes is not None else np.tile(Z, (len(p.points), 1))
            foot = p.points - ax * (dz / np.maximum(ax[:, 2:3], 1e-6))
            own = _signed(rl, p.points[:, :2])
            step = np.where(own > -w, _signed(rb, foot[:, :2]) - own, 0.0)
            i = int(np.argmax(step))
            if step[i] > worst:
                worst, where = float(step[i]), p.points[i]
        if where is not None and worst > limit + _TOL_MM:
            out.append({"layer": layer.index, "z_mm": round(float(layer.z_mm), 3),
                        "step_out_mm": round(worst, 3), "limit_mm": round(float(limit), 3),
                        "at": [round(float(v), 2) for v in where]})
    return out


def overhang_message(found: list[dict[str, Any]]) -> str:
    head = "; ".join(f"layer {f['layer']} (z {f['z_mm']} mm) steps out {f['step_out_mm']} mm at "
                     f"({f['at'][0]}, {f['at'][1]}) > {f['limit_mm']} mm" for f in found[:6])
    more = f"; and {len(found) - 6} more" if len(found) > 6 else ""
    return f"{len(found)} layer(s) break the overhang rule: {head}{more}"


# --- nozzle collision ------------------------------------------------------------------------------

def _sample(points: np.ndarray, step: float) -> np.ndarray:
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.vstack(out)


def collisions(job: Job, nozzle: Nozzle, first_only: bool = True) -> list[dict[str, Any]]:
    """Points where the nozzle cone would hit the part built so far (bead centre lines)."""
    from scipy.spatial import cKDTree  # lazy: only a 5-axis plan with a nozzle loads scipy (start-up time)

    tan_h = np.tan(np.radians(nozzle.half_angle_deg))
    built: list[np.ndarray] = []
    hits: list[dict[str, Any]] = []
    for layer in job.layers:
        for pi, p in enumerate(layer.passes):
            if built:
                cloud = np.vstack(built)
                tree = cKDTree(cloud)
                ax = p.axes if p.axes is not None else np.tile(Z, (len(p.points), 1))
                tips = p.points + ax * nozzle.standoff_mm
                for k, cand in enumerate(tree.query_ball_point(tips, nozzle.length_mm)):
                    if not cand:
                        continue
                    v = cloud[cand] - tips[k]
                    axial = v @ ax[k]
                    radial = np.linalg.norm(v - axial[:, None] * ax[k], axis=1)
                    bad = (axial > 0) & (axial < nozzle.length_mm) & (radial < axial * tan_h + layer.height_mm / 2)
                    if bad.any():
                        hits.append({"layer": layer.index, "pass": pi, "point": k,
                                     "at": [round(float(v), 2) for v in p.points[k]],
                                     "hits": [round(float(v), 2) for v in cloud[cand][bad][0]]})
                        if first_only:
                            return hits
                        break
            built.append(_sample(p.points, max(0.5 * p.width_mm, 0.2)))
    return hits


def collision_message(hit: dict[str, Any]) -> str:
    return (f"the nozzle would hit the part: layer {hit['layer']} pass {hit['pass']} point {hit['point']} at "
            f"({hit['at'][0]}, {hit['at'][1]}, {hit['at'][2]}) touches the bead at ({hit['hits'][0]}, "
            f"{hit['hits'][1]}, {hit['hits'][2]}); lower --tilt-limit, change the part's orientation or the nozzle")


# --- the pipeline step -------------------------------------------------------------------------------

def apply(job: Job, opt: FiveAxisOptions | None, allow_overhang: bool = False,
          regions: list[shapely.Geometry] | None = None) -> Job:
    """Plan step after the beads: 5-axis axes (opt given) and the overhang rule; summary records both.

    `regions`: each layer's sliced outline (shapely), else the outline of its beads.
    """
    three = overhangs(job, opt.max_overhang_deg if opt else 30.0, regions)
    summary = dict(job.summary)
    rule = {"max_overhang_deg": opt.max_overhang_deg if opt else 30.0, "three_axis_layers": three}
    if opt is None:
        if three and not allow_overhang:
            raise OverhangError(overhang_message(three) + "; plan with --five-axis or accept with --allow-overhang")
        rule["remaining"] = three
        summary["overhang"] = rule
        return dataclasses.replace(job, summary=summary)
    out = tool_axes(job, opt, regions)
    remaining = overhangs(out, opt.max_overhang_deg, regions)
    rule["remaining"] = remaining
    if remaining and not allow_overhang:
        raise OverhangError(overhang_message(remaining) + f" even tilted up to {opt.tilt_limit_deg:g}°; "
                            "raise kinematics.tilt_limit_deg or accept with --allow-overhang")
    if opt.nozzle is not None:
        hit = collisions(out, opt.nozzle)
        if hit:
            raise CollisionError(collision_message(hit[0]))
    tilts = [float(np.degrees(np.arccos(np.clip(p.axes[:, 2], -1, 1))).max()) for L in out.layers for p in L.passes
             if p.axes is not None]
    summary["overhang"] = rule
    summary["five_axis"] = {"tilt_limit_deg": opt.tilt_limit_deg, "max_tilt_deg": round(max(tilts, default=0.0), 2)}
    return dataclasses.replace(out, summary=summary)

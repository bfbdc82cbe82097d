"""Plan quality per layer: coverage, underfill, overfill, planned volume; and the job summary."""
from __future__ import annotations

from typing import Any

from dataclasses import dataclass

import numpy as np
import shapely

from planner.nearnet import side_stock
from planner.path2d import Path2D

TRAVEL_MM_MIN = 6000.0  # assumed torch travel speed between beads (arc off)
ARC_START_S = 1.5  # gas pre-flow + ignition + crater fill + post-flow per bead, assumed


@dataclass(frozen=True)
class LayerQuality:
    area_mm2: float
    covered_mm2: float
    footprint_mm2: float
    overfill_mm2: float  # footprint outside the contour itself
    volume_mm3: float
    deposit_mm: float
    layer_volume_mm3: float = 0.0  # layer area x layer height, what the beads should fill
    # unfilled areas larger than one bead's footprint (π·w²/4): (x, y, area mm², width mm) each
    gaps: tuple[tuple[float, float, float, float], ...] = ()
    stock: tuple[float, float] | None = None  # near-net: (min, max) side stock from the net contour, mm
    largest: tuple[tuple[float, float, float, float], ...] = ()  # the 3 largest unfilled pieces, any size

    @property
    def coverage(self) -> float:
        return self.covered_mm2 / self.area_mm2 if self.area_mm2 > 0 else 1.0


def layer_quality(region: shapely.Geometry, paths: list[Path2D], width: float, height: float,
                  net: shapely.Geometry | None = None) -> LayerQuality:
    """Coverage = share of the layer inside the union of bead footprints (round-capped, at width)."""
    area = float(region.area)
    if not paths:
        return LayerQuality(area, 0.0, 0.0, 0.0, 0.0, 0.0, area * height)
    lines = np.array([shapely.linestrings(p.points) for p in paths], dtype=object)
    widths = np.array([p.width_mm for p in paths])
    fp = shapely.union_all(shapely.buffer(lines, widths / 2.0, quad_segs=4))
    covered = float(shapely.intersection(fp, region).area)
    outside = float(shapely.difference(fp, region).area)
    # what no bead covers: the pieces over one bead's footprint are features; the three largest
    # of any size say where a layer under --min-coverage is short
    rest = unfilled(region, fp, width, 0.05 * width * width, 0.0) if covered < area - 0.05 * width * width else ()
    gaps = tuple(g for g in rest if g[2] > 0.25 * np.pi * width * width and g[3] >= 0.05 * width)
    lengths = shapely.length(lines)
    # The metal the passes lay (mass balance): each bead's share of the layer times its length.
    share = np.array([p.share_mm for p in paths])
    return LayerQuality(area, covered, float(fp.area), outside, float(np.sum(share * lengths) * height),
                        float(lengths.sum()), area * height, gaps,
                        side_stock(net, fp, width) if net is not None else None, rest[:3])


def unfilled(region: shapely.Geometry, footprint: shapely.Geometry, width: float,
             min_area: float | None = None, sliver: float = 0.05) -> tuple[tuple[float, float, float, float], ...]:
    """The pieces of the layer no bead covers larger than `min_area` (default one bead's footprint, π·w²/4):
    (x, y) of a point inside each, its area and its mean width (2·area / perimeter), largest first.
    Slivers thinner than 5 % of a bead on average (the seam between two touching beads) are the
    neighbours' flow, not features."""
    rest = shapely.get_parts(shapely.difference(region, footprint))
    if len(rest) == 0:
        return ()
    areas = shapely.area(rest)
    big = rest[areas > (0.25 * np.pi * width * width if min_area is None else min_area)]
    out = []
    for g in big:
        mean_w = 2.0 * float(g.area) / max(float(g.length), 1e-9)
        if mean_w < sliver * width:
            continue
        c = g.representative_point()
        out.append((round(float(c.x), 1), round(float(c.y), 1), round(float(g.area), 1), round(mean_w, 2)))
    return tuple(sorted(out, key=lambda t: (-t[2], t[0], t[1])))


def gap_message(index: int, gap: tuple[float, float, float, float]) -> str:
    x, y, a, wd = gap
    return f"layer {index}: unfilled area at ({x:.1f}, {y:.1f}), {a:.0f} mm2, about {wd:.2f} mm wide"


def summarise(qualities: list[LayerQuality], n_passes: int, time_s: float) -> dict[str, Any]:
    area = sum(q.area_mm2 for q in qualities)
    cov = sum(q.covered_mm2 for q in qualities) / area if area > 0 else 1.0
    fp = sum(q.footprint_mm2 for q in qualities)
    return {
        "layers": len(qualities),
        "passes": n_passes,
        "arc_starts": n_passes,
        "deposit_length_mm": round(sum(q.deposit_mm for q in qualities), 1),
        "volume_mm3": round(sum(q.volume_mm3 for q in qualities), 1),
        "coverage": round(cov, 5),
        "coverage_min": round(min((q.coverage for q in qualities), default=1.0), 5),
        "underfill": round(1.0 - cov, 5),
        "overfill": round(sum(q.overfill_mm2 for q in qualities) / fp, 5) if fp > 0 else 0.0,
        "layer_volume_mm3": round(sum(q.layer_volume_mm3 for q in qualities), 1),
        "est_time_s": round(time_s, 1),
    }

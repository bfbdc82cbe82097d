"""Perimeters: closed beads around every boundary by inward offsets at the step-over (Fang 2019)."""
from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from planner.path2d import Path2D
from planner.regions import polygons_of
from planner.ring_spacing import END_REACH, spaced

THIN_FACTOR = 1.5  # regions narrower than about 1.5 bead widths get one centre-line bead


def split_thin(poly: Polygon, width: float) -> tuple[list[Polygon], list[Polygon]]:
    """(thick, thin): thin = what an opening of diameter 1.5·w removes (walls narrower than 1.5 w)."""
    r = 0.5 * THIN_FACTOR * width
    opened = poly.buffer(-r, join_style="mitre").buffer(r, join_style="mitre")
    thick = [p for p in polygons_of(opened.intersection(poly)) if p.area > 0.05 * width * width]
    if thick and poly.area - sum(p.area for p in thick) < 0.05 * width * width:
        # what the opening took is less than half the smallest thin piece kept below: no overlay
        # of the two nearly coincident outlines (slow, issue 28) to find only slivers
        return thick, []
    rest = poly.difference(shapely.union_all(thick)) if thick else poly
    # Slivers left by the opening along straight edges are numerical, not features.
    thin = [p for p in polygons_of(rest) if p.area > 0.1 * width * width
            and not p.buffer(-0.05 * width).is_empty]
    return thick, thin


def perimeter_loops(poly: Polygon, width: float, step: float, count: int | None,
                    quad_segs: int = 6, min_spacing: float | None = None, min_length: float | None = None
                    ) -> tuple[list[list[Path2D]], float, list[Polygon]]:
    """Loops per offset level (outermost first), the inset of the innermost bead centres, and
    the slivers where a loop would overlap itself (Fang 2019: removed, given a centre line).

    The first loop's centre is half a bead inside the contour (the bead's edge on the contour);
    `count=None` offsets until the loops meet (Fang's composite path). Two rings of a level that
    run closer than the stable spacing (a hole's ring beside the outside's where the region
    narrows) keep one ring whole and the other trimmed there (planner.ring_spacing).
    """
    min_sp = 0.9 * step if min_spacing is None else min_spacing
    levels: list[list[Path2D]] = []
    slivers: list[Polygon] = []
    k = 0
    inset = 0.5 * width
    while count is None or k < count:
        off = 0.5 * width + k * step
        geom = poly.buffer(-off, quad_segs=quad_segs)
        pieces = [orient(p, 1.0) for p in polygons_of(geom) if p.area > 0.02 * width * width]
        # A piece narrower than the stable spacing: its loop's two sides would pile up on each other.
        # (5 % slack: a loop pair exactly at the stable limit is kept.)
        sliver = [p.buffer(-0.475 * min_sp).is_empty for p in pieces]
        slivers += [p for p, s in zip(pieces, sliver) if s]
        pieces = [p for p, s in zip(pieces, sliver) if not s]
        if not pieces:
            break
        loops = []
        for p in pieces:
            for ring in (p.exterior, *p.interiors):
                pts = np.asarray(ring.coords)[:, :2]
                # The outermost bead has no neighbour outside: it fills half a width plus half a step.
                share = 0.5 * (width + step) if k == 0 else step
                loops.append(Path2D("perimeter", pts, width, closed=True, share_mm=share))
        min_len = 2.0 * width if min_length is None else min_length
        levels.append(spaced(loops, min_sp, END_REACH * width, min_len, None if k == 0 else step))
        inset = off
        k += 1
    return levels, inset, slivers

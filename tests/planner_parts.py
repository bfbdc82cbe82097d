"""Test parts for the planner, generated (never committed as big files)."""
from __future__ import annotations

import numpy as np
import trimesh
from shapely.geometry import Point, box

from planner.extrude import extrude, stack


def plate_with_holes() -> trimesh.Trimesh:
    """120 x 80 x 6 mm plate with three round holes of different sizes."""
    sec = box(0, 0, 120, 80)
    for x, y, r in ((30, 40, 10), (70, 25, 6), (90, 55, 12)):
        sec = sec.difference(Point(x, y).buffer(r, quad_segs=24))
    return extrude(sec, 6.0)


def thin_wall(thickness: float = 5.0) -> trimesh.Trimesh:
    """A straight wall 80 mm long, `thickness` thick (narrower than 1.5 beads), 10 mm tall."""
    return extrude(box(0, 0, 80, thickness), 10.0)


def islands() -> trimesh.Trimesh:
    """Three separate blocks and a ring with an island standing in its hole."""
    ring = Point(0, 0).buffer(30, quad_segs=24).difference(Point(0, 0).buffer(20, quad_segs=24))
    parts = [extrude(box(50, -20, 80, 10), 5.0), extrude(box(90, -20, 110, 30), 5.0),
             extrude(box(-60, 40, -10, 60), 5.0), extrude(ring, 5.0),
             extrude(Point(0, 0).buffer(10, quad_segs=24), 5.0)]
    return stack(*parts)


def overhang() -> trimesh.Trimesh:
    """An L in elevation: a 40 x 40 column with a 70 x 40 slab cantilevered on top."""
    return stack(extrude(box(0, 0, 40, 40), 12.0), extrude(box(0, 0, 70, 40), 6.0, z0=12.0))


def sphere_with_holes(fraction: float = 0.001, seed: int = 3) -> trimesh.Trimesh:
    """An icosphere (r 40 mm, 81,920 faces) with `fraction` of its faces deleted."""
    m = trimesh.creation.icosphere(subdivisions=6, radius=40.0)
    rng = np.random.default_rng(seed)
    keep = np.ones(len(m.faces), dtype=bool)
    keep[rng.choice(len(m.faces), int(round(fraction * len(m.faces))), replace=False)] = False
    return trimesh.Trimesh(m.vertices, m.faces[keep], process=False)

"""Prism meshes from shapely polygons (demo and test parts), without a triangulation engine."""
from __future__ import annotations

from typing import Any

import numpy as np
import shapely
import trimesh
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient


def extrude(poly: Polygon, height: float, z0: float = 0.0) -> trimesh.Trimesh:
    """A closed, outward-wound prism of `poly` from z0 to z0 + height."""
    poly = orient(poly, 1.0)
    tris = shapely.get_parts(shapely.constrained_delaunay_triangles(poly))
    tri_xy = np.array([np.asarray(t.exterior.coords)[:3] for t in tris])
    # Orient every cap triangle counter-clockwise (seen from +z).
    e1, e2 = tri_xy[:, 1] - tri_xy[:, 0], tri_xy[:, 2] - tri_xy[:, 0]
    cross = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    tri_xy[cross < 0] = tri_xy[cross < 0][:, ::-1]
    top = np.concatenate([tri_xy, np.full((*tri_xy.shape[:2], 1), z0 + height)], axis=2)
    bottom = np.concatenate([tri_xy[:, ::-1], np.full((*tri_xy.shape[:2], 1), z0)], axis=2)
    walls = []
    for ring in (poly.exterior, *poly.interiors):
        c = np.asarray(ring.coords)[:, :2]
        a, b = c[:-1], c[1:]
        walls.append(np.stack([_at(a, z0), _at(b, z0), _at(b, z0 + height)], axis=1))
        walls.append(np.stack([_at(a, z0), _at(b, z0 + height), _at(a, z0 + height)], axis=1))
    triangles = np.concatenate([top, bottom, *walls])
    tri: Any = trimesh.triangles  # trimesh's functions are not annotated
    return trimesh.Trimesh(**tri.to_kwargs(triangles), process=True)


def _at(p: np.ndarray, z: float) -> np.ndarray:
    return np.column_stack([p, np.full(len(p), z)])


def stack(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    """Several disjoint solids as one mesh."""
    util: Any = trimesh.util
    out: trimesh.Trimesh = util.concatenate(meshes)
    return out

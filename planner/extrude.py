"""Prism meshes from shapely polygons (demo and test parts), without a triangulation engine."""
from __future__ import annotations

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
        lo = lambda p: np.column_stack([p, np.full(len(p), z0)])  # noqa: E731
        hi = lambda p: np.column_stack([p, np.full(len(p), z0 + height)])  # noqa: E731
        walls.append(np.stack([lo(a), lo(b), hi(b)], axis=1))
        walls.append(np.stack([lo(a), hi(b), hi(a)], axis=1))
    triangles = np.concatenate([top, bottom, *walls])
    mesh = trimesh.Trimesh(**trimesh.triangles.to_kwargs(triangles), process=True)
    return mesh


def stack(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    """Several disjoint solids as one mesh."""
    return trimesh.util.concatenate(meshes)

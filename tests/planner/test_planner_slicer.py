"""Slicer: all layers at once, closed loops with the material on the left, facet normals, gap closing."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
import trimesh
from shapely.geometry import Point, box

from core.config import load_material
from core.errors import MeshError
from planner.extrude import extrude
from planner.mesh import prepare_mesh
from planner.plan import PlanOptions, plan_part
from planner.slicer import slice_levels, slice_mesh


def _signed_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def test_sphere_sections_match_the_circle_area_and_carry_radial_normals():
    pm = prepare_mesh(trimesh.creation.icosphere(subdivisions=5, radius=30))
    levels = slice_levels(pm.extents[2], 2.0)
    assert len(levels) == 30 and levels[0] == pytest.approx(1.0)
    slices = slice_mesh(pm.vertices, pm.faces, pm.face_normals, levels)
    for sl in slices:
        assert len(sl.contours) == 1 and sl.contours[0].closed
        c = sl.contours[0]
        r2 = 30.0 ** 2 - (sl.z_mm - 30.0) ** 2
        assert _signed_area(c.points) == pytest.approx(np.pi * r2, rel=0.01)  # CCW: positive
        radial = np.column_stack([c.points, np.full(len(c.points), sl.z_mm - 30.0)])
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        assert np.min(np.einsum("ij,ij->i", radial, c.normals)) > 0.95


def test_holes_run_clockwise_and_outer_counter_clockwise():
    sec = box(0, 0, 70, 70).difference(Point(35, 35).buffer(17.5, quad_segs=32))
    pm = prepare_mesh(extrude(sec, 30))
    sl = slice_mesh(pm.vertices, pm.faces, pm.face_normals, np.array([15.0]))[0]
    areas = sorted(_signed_area(c.points) for c in sl.contours)
    assert areas[0] == pytest.approx(-np.pi * 17.5 ** 2, rel=0.01)
    assert areas[1] == pytest.approx(4900.0, rel=1e-6)


def test_vertex_exactly_on_a_plane_still_gives_closed_loops():
    # Layer planes at 1, 3, 5 mm cut through vertices of this mesh at z = 3 exactly.
    lower = extrude(box(0, 0, 20, 20), 3.0)
    upper = extrude(box(5, 5, 15, 15), 3.0, z0=3.0)
    pm = prepare_mesh(trimesh.util.concatenate([lower, upper]))
    slices = slice_mesh(pm.vertices, pm.faces, pm.face_normals, np.array([1.0, 3.0, 5.0]))
    assert all(c.closed for sl in slices for c in sl.contours)
    assert shapely.Polygon(slices[2].contours[0].points).area == pytest.approx(100.0)


def test_deleted_faces_are_bridged_and_counted():
    m = trimesh.creation.icosphere(subdivisions=5, radius=30)
    keep = np.ones(len(m.faces), bool)
    keep[np.random.default_rng(1).choice(len(keep), 40, replace=False)] = False
    vertices, faces = m.vertices, m.faces[keep]
    normals = trimesh.Trimesh(vertices, faces, process=False).face_normals
    slices = slice_mesh(vertices, faces, normals, slice_levels(60.0, 2.0), gap_tolerances=(1e-6, 0.5, 3.0))
    contours = [c for sl in slices for c in sl.contours]
    assert all(c.closed for c in contours)
    assert sum(c.gap_mm > 0 for c in contours) >= 5  # the holes really were crossed and bridged


def test_open_contour_beyond_tolerance_fails_with_the_list():
    # A tube with a long slot cut through its wall: every layer's contour is open by 10 mm.
    ring = Point(0, 0).buffer(30).difference(Point(0, 0).buffer(20))
    m = extrude(ring, 10.0)
    centres = m.triangles_center
    slot = (np.abs(centres[:, 1]) < 5.0) & (centres[:, 0] > 0) & (centres[:, 2] > 0.01) & (centres[:, 2] < 9.99)
    m = trimesh.Trimesh(m.vertices, m.faces[~slot], process=False)
    with pytest.raises(MeshError, match=r"open contour\(s\).*layer 0 \(z 0\.33 mm\): open from"):
        plan_part(m, PlanOptions(width_mm=6.0), load_material("inconel718-1.0mm"))

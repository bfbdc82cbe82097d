"""Mesh intake: units, repairs reported, orientation, and clear errors for meshes that cannot be planned."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from shapely.geometry import box

from core.errors import MeshError
from planner.extrude import extrude
from planner.mesh import check_size, prepare_mesh, read_mesh


def _write(tmp_path, mesh: trimesh.Trimesh, name: str = "part.stl"):
    p = tmp_path / name
    data = mesh.export(file_type=p.suffix.lstrip("."))
    p.write_bytes(data.encode() if isinstance(data, str) else data)
    return p


def test_inch_file_is_scaled_to_mm_and_put_on_z0(tmp_path):
    m = extrude(box(0, 0, 2, 1), 0.5)
    m.apply_translation([0, 0, 3.0])
    pm = read_mesh(_write(tmp_path, m), units="inch")
    assert np.allclose(pm.extents, [50.8, 25.4, 12.7])
    assert pm.vertices[:, 2].min() == 0.0
    assert pm.source.units == "inch" and len(pm.source.sha256) == 64


@pytest.mark.parametrize("ext", ["obj", "3mf"])
def test_other_formats_load(tmp_path, ext):
    pm = read_mesh(_write(tmp_path, extrude(box(0, 0, 30, 20), 10), f"part.{ext}"))
    assert np.allclose(pm.extents, [30, 20, 10]) and pm.watertight


def test_inside_out_mesh_is_inverted_and_reported():
    m = extrude(box(0, 0, 30, 20), 10)
    m.invert()
    pm = prepare_mesh(m)
    assert any("inverted" in r for r in pm.repairs)
    # Outward normals again: the +x wall's faces point to +x.
    centres = pm.vertices[pm.faces].mean(axis=1)
    right = centres[:, 0] > 29.99
    assert np.all(pm.face_normals[right, 0] > 0.99)


def test_small_hole_is_filled_and_reported():
    m = trimesh.creation.icosphere(subdivisions=3, radius=20)
    m = trimesh.Trimesh(m.vertices, m.faces[1:], process=False)
    pm = prepare_mesh(m)
    assert pm.watertight
    assert any("filled" in r for r in pm.repairs)


def test_empty_file_is_a_clear_error(tmp_path):
    p = tmp_path / "empty.stl"
    p.write_bytes(b"")
    with pytest.raises(MeshError, match="empty"):
        read_mesh(p)
    p.write_bytes(b"solid empty\nendsolid empty\n")
    with pytest.raises(MeshError, match="no triangles"):
        read_mesh(p)


def test_shared_empty_stl_is_a_clear_error(shared_parts):
    with pytest.raises(MeshError, match="no triangles"):
        read_mesh(shared_parts / "empty.stl")


def test_garbage_file_is_a_clear_error(tmp_path):
    p = tmp_path / "junk.stl"
    p.write_bytes(b"\x00\x01garbage" * 3)
    with pytest.raises(MeshError, match="junk.stl"):
        read_mesh(p)


def test_part_smaller_than_a_bead_suggests_inches(tmp_path):
    pm = read_mesh(_write(tmp_path, extrude(box(0, 0, 5, 2.4), 1.4)))
    with pytest.raises(MeshError, match="smaller than one bead.*--units .*inch"):
        check_size(pm, width_mm=6.0, layer_mm=0.66)

"""Mesh intake: read STL/OBJ/3MF at the edge, scale to mm, check and repair, put the part on z = 0."""
from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from planner.errors import InputError, MeshError

UNITS_MM = {"mm": 1.0, "inch": 25.4}
FORMATS = ("stl", "obj", "3mf", "ply", "off")


@dataclass(frozen=True)
class MeshSource:
    """Where the mesh came from: file name, SHA-256 of its bytes, unit it was read in."""

    file: str
    sha256: str
    units: str


@dataclass(frozen=True)
class PreparedMesh:
    """A checked mesh in mm with its lowest point on z = 0, and what was repaired."""

    vertices: np.ndarray  # (V, 3) float64, mm
    faces: np.ndarray  # (F, 3) int64
    face_normals: np.ndarray  # (F, 3) unit outward normals
    repairs: tuple[str, ...]
    watertight: bool
    source: MeshSource

    @property
    def extents(self) -> np.ndarray:
        return np.ptp(self.vertices, axis=0) if len(self.vertices) else np.zeros(3)


def read_mesh(path: str | Path, units: str = "mm") -> PreparedMesh:
    """Read a mesh file (the only I/O of the planner) and prepare it; bad files raise MeshError."""
    p = Path(path)
    if units not in UNITS_MM:
        raise InputError(f"--units: '{units}' is not a unit; use mm or inch")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise MeshError(f"{p}: cannot read the mesh file ({exc.strerror or exc})") from exc
    ext = p.suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise MeshError(f"{p}: unknown mesh format '.{ext}'; export the part as STL, OBJ or 3MF")
    mesh = _parse(data, ext, p)
    source = MeshSource(file=p.name, sha256=hashlib.sha256(data).hexdigest(), units=units)
    return prepare_mesh(mesh, units, source)


def _parse(data: bytes, ext: str, p: Path) -> trimesh.Trimesh:
    if len(data) == 0:
        raise MeshError(f"{p}: the file is empty (0 bytes); export the part again")
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=ext, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds on garbage input
        raise MeshError(f"{p}: not a readable {ext.upper()} mesh ({type(exc).__name__}: {exc}); "
                        "check the file or export it again") from exc
    if isinstance(loaded, trimesh.Scene):  # force="mesh" returns an empty Scene for no geometry
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geoms) if geoms else trimesh.Trimesh()
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{p}: the mesh has no triangles; export the part again as a solid")
    return loaded


def prepare_mesh(mesh: trimesh.Trimesh, units: str = "mm", source: MeshSource | None = None) -> PreparedMesh:
    """Scale to mm, merge, drop degenerate/duplicate faces, fix winding, fill small holes, z0 = 0."""
    name = source.file if source else "mesh"
    if len(mesh.faces) == 0:
        raise MeshError(f"{name}: the mesh has no triangles; export the part again as a solid")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{name}: the mesh has NaN or infinite coordinates; export it again")
    mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64) * UNITS_MM[units],
                           faces=np.asarray(mesh.faces, dtype=np.int64), process=False)
    repairs: list[str] = []
    nv = len(mesh.vertices)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    if len(mesh.vertices) < nv:
        repairs.append(f"merged {nv - len(mesh.vertices)} duplicate vertices")
    keep = mesh.nondegenerate_faces(height=1e-9)
    if not keep.all():
        repairs.append(f"removed {int((~keep).sum())} degenerate faces")
        mesh.update_faces(keep)
    uniq = mesh.unique_faces()
    if not uniq.all():
        repairs.append(f"removed {int((~uniq).sum())} duplicate faces")
        mesh.update_faces(uniq)
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise MeshError(f"{name}: every triangle is degenerate (zero area); export the part again")
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        repairs.append("fixed inconsistent face winding")
    if not mesh.is_watertight:
        before = len(mesh.faces)
        trimesh.repair.fill_holes(mesh)
        if len(mesh.faces) > before:
            repairs.append(f"filled small holes with {len(mesh.faces) - before} faces")
    watertight = bool(mesh.is_watertight)
    if watertight and mesh.volume < 0:
        mesh.invert()
        repairs.append("inverted normals (the mesh was inside out)")
    elif not watertight:
        # An open mesh has no signed volume; orient by the majority of faces pointing outward.
        centre = mesh.vertices.mean(axis=0)
        outward = np.einsum("ij,ij->i", mesh.triangles_center - centre, mesh.face_normals)
        if np.sum(mesh.area_faces * np.sign(outward)) < 0:
            mesh.invert()
            repairs.append("inverted normals (most faces pointed inward)")
        repairs.append("mesh is not closed after repair: layers are closed by the slicer's gap tolerance")
    vertices = np.array(mesh.vertices, dtype=np.float64)
    vertices[:, 2] -= vertices[:, 2].min()
    faces = np.array(mesh.faces, dtype=np.int64)
    normals = np.array(mesh.face_normals, dtype=np.float64)
    if source is None:
        source = MeshSource(file="mesh", sha256=hashlib.sha256(vertices.tobytes() + faces.tobytes()).hexdigest(),
                            units=units)
    return PreparedMesh(vertices, faces, normals, tuple(repairs), watertight, source)


def check_size(mesh: PreparedMesh, width_mm: float, layer_mm: float) -> None:
    """A part smaller than one bead (in plan or in height) cannot be deposited: MeshError."""
    ex = mesh.extents
    hint = "; if the file is in inches, use --units inch" if mesh.source.units == "mm" else ""
    if max(ex[0], ex[1]) < width_mm:
        raise MeshError(f"{mesh.source.file}: the part is {ex[0]:.3g} x {ex[1]:.3g} mm in plan, smaller than "
                        f"one bead ({width_mm:g} mm wide){hint}")
    if ex[2] < 0.5 * layer_mm:
        raise MeshError(f"{mesh.source.file}: the part is {ex[2]:.3g} mm tall, less than half a layer "
                        f"({layer_mm:g} mm){hint}")

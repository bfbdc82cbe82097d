"""Mesh intake: read STL/OBJ/3MF at the edge, scale to mm, check and repair, put the part on z = 0."""
from __future__ import annotations

import hashlib
import io
from typing import Any
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planner import limits
from core.errors import InputError, MeshError

UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "inch": 25.4}
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
    z_shift_mm: float = 0.0  # how far the part was lowered to put it on z = 0 (`--frame cad` adds it back)

    @property
    def extents(self) -> np.ndarray:
        return np.ptp(self.vertices, axis=0) if len(self.vertices) else np.zeros(3)


def read_mesh(path: str | Path, units: str = "mm") -> PreparedMesh:
    """Read a mesh file (the only I/O of the planner) and prepare it; bad files raise MeshError."""
    p = Path(path)
    if units not in UNITS_MM:
        raise InputError(f"--units: '{units}' is not a unit; use mm, cm, m or inch")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise MeshError(f"{p}: cannot read the mesh file ({exc.strerror or exc})") from exc
    ext = p.suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise MeshError(f"{p}: unknown mesh format '.{ext}'; export the part as STL, OBJ or 3MF")
    if len(data) == 0:
        raise MeshError(f"{p}: the file is empty (0 bytes); export the part again")
    source = MeshSource(file=p.name, sha256=hashlib.sha256(data).hexdigest(), units=units)
    limits.check_file(p.name, len(data), _binary_count(data) if ext == "stl" else None)
    tri = _binary_stl(data) if ext == "stl" else None
    if tri is not None:
        if len(tri) == 0:
            raise MeshError(f"{p}: the mesh has no triangles; export the part again as a solid")
        vertices, faces = _weld(tri)
        # the distinct corners, in the file's single precision as before: the same verdict and figure
        limits.check_vertices(p.name, vertices.astype(np.float32) * UNITS_MM[units], len(tri))
        fast = _prepare_clean(vertices, faces, units, source)
        if fast is not None:
            return fast
        import trimesh  # lazy: the fast binary-STL path never loads trimesh (start-up time)

        return prepare_mesh(trimesh.Trimesh(vertices, faces, process=False), units, source)
    return prepare_mesh(_parse(data, ext, p), units, source)


def _binary_count(data: bytes) -> int | None:
    """The triangle count of a binary STL whose size matches its header, else None."""
    if len(data) >= 84 and len(data) == 84 + 50 * int.from_bytes(data[80:84], "little"):
        return int.from_bytes(data[80:84], "little")
    return None


def _binary_stl(data: bytes) -> np.ndarray | None:
    """Triangles (n, 3, 3) of a binary STL, or None when the bytes are not one (ASCII STL)."""
    if len(data) < 84:
        return None
    n = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    if len(data) != 84 + 50 * n:
        return None
    rec = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    return np.frombuffer(data, dtype=rec, count=n, offset=84)["v"]


def _weld(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shared vertices from exactly repeated corner coordinates (STL repeats them bit for bit).

    The vertices come in the order of a stable sort of the corners' 64-bit hashes (first corner
    of each): the same numbering whichever way it is computed."""
    v = np.ascontiguousarray(tri.reshape(-1, 3), dtype=np.float32) + np.float32(0.0)  # -0.0 -> 0.0
    b32 = v.view(np.uint32)
    # One 64-bit key per corner (a hash of its three float bit patterns); equal coordinates give
    # equal keys, and a collision is caught below by comparing the bits.
    h = b32[:, 0] * np.uint64(0x9E3779B185EBCA87)
    h ^= b32[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
    h ^= b32[:, 2] * np.uint64(0x165667B19E3779F9)
    order, sh = _stable_order(h)
    new = np.empty(len(sh), dtype=bool)
    new[0] = True
    np.not_equal(sh[1:], sh[:-1], out=new[1:])
    del sh
    ids = np.cumsum(new) - 1
    first = order[new]
    inverse = np.empty(len(v), dtype=np.int64)
    inverse[order] = ids
    rows = v.view(np.dtype((np.void, 12))).ravel()  # a corner's 12 bytes, compared at once
    if np.any(rows != rows[first][inverse]):  # a hash collision: sort on the bits themselves
        return _weld_exact(v)
    return v[first].astype(np.float64), inverse.reshape(-1, 3)


def _stable_order(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`np.argsort(h, kind="stable")` and `h` in that order, by a plain sort of keys that carry the
    index in their low bits (the high bits of the hash above it), put right where two hashes
    differ only in the bits dropped (rare: an almost sorted array sorts in one pass)."""
    n = len(h)
    shift = np.uint64(max((n - 1).bit_length(), 1))
    key = (h >> shift) << shift
    key |= np.arange(n, dtype=np.uint64)
    key.sort()
    order = (key & ((np.uint64(1) << shift) - np.uint64(1))).astype(np.intp)
    del key
    sh = h[order]
    if n > 1 and np.any(sh[1:] < sh[:-1]):
        fix = np.argsort(sh, kind="stable")
        order, sh = order[fix], sh[fix]
    return order, sh


def _weld_exact(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shared vertices by a sort on the coordinates' bits (no hash): when two hashes collide."""
    b = v.view(np.uint32)
    order = np.lexsort((b[:, 2], b[:, 1], b[:, 0]))
    sb = b[order]
    new = np.empty(len(sb), dtype=bool)
    new[0] = True
    new[1:] = np.any(sb[1:] != sb[:-1], axis=1)
    ids = np.cumsum(new) - 1
    first = order[new]
    inverse = np.empty(len(v), dtype=np.int64)
    inverse[order] = ids
    return v[first].astype(np.float64), inverse.reshape(-1, 3)


def _prepare_clean(vertices: np.ndarray, faces: np.ndarray, units: str, source: MeshSource) -> PreparedMesh | None:
    """The fast path for a clean mesh (closed, consistently wound, no degenerate face); else None."""
    if not np.all(np.isfinite(vertices)):
        return None
    f = faces
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])):
        return None
    vertices = vertices * UNITS_MM[units]
    p0, cross, area2 = _face_cross(vertices, f)
    if np.any(area2 <= 1e-12 * max(float(np.ptp(vertices)), 1.0) ** 2):
        return None
    nv = np.int64(len(vertices))
    a, b = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)
    key = np.sort(a * nv + b)
    if np.any(key[1:] == key[:-1]):
        return None  # an edge used twice the same way: inconsistent winding or non-manifold
    if not np.array_equal(np.sort(b * nv + a), key):
        return None  # an edge without its twin: open
    repairs: list[str] = []
    volume = float(np.einsum("ij,ij->i", p0, cross).sum()) / 6.0
    normals = cross / area2[:, None]
    if volume < 0:
        f = f[:, ::-1].copy()
        normals = -normals
        repairs.append("inverted normals (the mesh was inside out)")
    vertices = vertices.copy()
    z0 = float(vertices[:, 2].min())
    vertices[:, 2] -= z0
    return PreparedMesh(vertices, np.ascontiguousarray(f, dtype=np.int64), normals, tuple(repairs), True, source, z0)


def _face_cross(vertices: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each face's first corner, edge cross product and its length: np.cross and np.linalg.norm's
    own arithmetic (the same bits), column by column without the (F, 3, 3) corner array."""
    p0 = np.take(vertices, f[:, 0], axis=0)
    e1 = np.take(vertices, f[:, 1], axis=0)
    e1 -= p0
    e2 = np.take(vertices, f[:, 2], axis=0)
    e2 -= p0
    cross = np.empty_like(e1)
    cross[:, 0] = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
    cross[:, 1] = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
    cross[:, 2] = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    c0, c1, c2 = cross[:, 0], cross[:, 1], cross[:, 2]
    area2 = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    return p0, cross, area2


def _parse(data: bytes, ext: str, p: Path) -> Any:
    import trimesh  # lazy: the fast binary-STL path never loads trimesh (start-up time)

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


def prepare_mesh(mesh: Any, units: str = "mm", source: MeshSource | None = None) -> PreparedMesh:
    """Scale to mm, merge, drop degenerate/duplicate faces, fix winding, fill small holes, z0 = 0."""
    import trimesh  # lazy: the fast binary-STL path never loads trimesh (start-up time)

    name = source.file if source else "mesh"
    if len(mesh.faces) == 0:
        raise MeshError(f"{name}: the mesh has no triangles; export the part again as a solid")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{name}: the mesh has NaN or infinite coordinates; export it again")
    mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64) * UNITS_MM[units],
                           faces=np.asarray(mesh.faces, dtype=np.int64), process=False)
    repairs: list[str] = []
    # Welding shared corners is how every STL is read, not a repair: it is not reported.
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
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
        repair: Any = trimesh.repair  # trimesh's functions are not annotated
        repair.fix_winding(mesh)
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
    z0 = float(vertices[:, 2].min())
    vertices[:, 2] -= z0
    faces = np.array(mesh.faces, dtype=np.int64)
    normals = np.array(mesh.face_normals, dtype=np.float64)
    if source is None:
        source = MeshSource(file="mesh", sha256=hashlib.sha256(vertices.tobytes() + faces.tobytes()).hexdigest(),
                            units=units)
    return PreparedMesh(vertices, faces, normals, tuple(repairs), watertight, source, z0)


def check_size(mesh: PreparedMesh, width_mm: float, layer_mm: float) -> None:
    """A part smaller than one bead (in plan or in height) cannot be deposited: MeshError."""
    ex = mesh.extents
    hint = "; if the file is in other units, use --units cm, m or inch" if mesh.source.units == "mm" else ""
    if max(ex[0], ex[1]) < width_mm:
        raise MeshError(f"{mesh.source.file}: the part is {ex[0]:.3g} x {ex[1]:.3g} mm in plan, smaller than "
                        f"one bead ({width_mm:g} mm wide){hint}")
    if ex[2] < 0.5 * layer_mm:
        raise MeshError(f"{mesh.source.file}: the part is {ex[2]:.3g} mm tall, less than half a layer "
                        f"({layer_mm:g} mm){hint}")

"""Bounded resources of planning: checks made before slicing, so no mesh can exhaust memory or
time (issue 14). The limits are stated here and in docs/input-limits.md."""
from __future__ import annotations

import numpy as np

from core.errors import MeshError
from planner.slicer import face_z_range

MAX_FACES = 5_000_000          # triangles of one mesh
MAX_TEXT_BYTES = 400_000_000   # an ASCII STL / OBJ / 3MF file (parsed by trimesh)
MAX_COORD_MM = 1.0e5           # |x|, |y|, |z| after the unit: 100 m, beyond any cell
MAX_EXTENT_MM = 5000.0         # bounding box of a part, any axis
MAX_LAYERS = 20_000
MAX_SEGMENTS = 30_000_000      # slice segments (≈ faces crossed per layer, summed): ~2 GB of arrays at most


def check_file(name: str, size: int, binary_faces: int | None) -> None:
    """Refuse a mesh file too large to load in bounded memory."""
    if binary_faces is not None and binary_faces > MAX_FACES:
        raise MeshError(f"{name}: {binary_faces} triangles, over the limit of {MAX_FACES}; decimate the mesh")
    if binary_faces is None and size > MAX_TEXT_BYTES:
        raise MeshError(f"{name}: {size} bytes of text mesh, over the limit of {MAX_TEXT_BYTES}; "
                        "export it as binary STL")


def check_vertices(name: str, vertices: np.ndarray, n_faces: int) -> None:
    """Refuse non-finite, absurdly large coordinates and too many faces."""
    if n_faces > MAX_FACES:
        raise MeshError(f"{name}: {n_faces} triangles, over the limit of {MAX_FACES}; decimate the mesh")
    v = np.asarray(vertices, dtype=np.float64)
    if v.size == 0:
        return
    with np.errstate(all="ignore"):
        big = float(np.max(np.abs(v)))
    if not np.isfinite(big):
        raise MeshError(f"{name}: the mesh has non-finite (NaN or infinite) coordinates; export it again")
    if big > MAX_COORD_MM:
        raise MeshError(f"{name}: a coordinate of {big:.3g} mm is beyond ±{MAX_COORD_MM:g} mm; "
                        "check the units (--units) or export the part again")


def check_before_slicing(name: str, vertices: np.ndarray, faces: np.ndarray, layer_mm: float,
                         workspace_mm: tuple[float, float, float] | None = None,
                         z_range: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Refuse a part larger than the workspace (or MAX_EXTENT_MM), or one whose layer or
    segment count would exceed the stated limits, before any slicing. `z_range`: each face's
    lowest and highest z (planner.slicer.face_z_range) when the caller has them."""
    check_vertices(name, vertices, len(faces))
    v = np.asarray(vertices, dtype=np.float64)
    ext = v.max(axis=0) - v.min(axis=0)
    room = np.minimum(np.asarray(workspace_mm, dtype=float), MAX_EXTENT_MM) if workspace_mm is not None \
        else np.full(3, MAX_EXTENT_MM)
    if np.any(ext > room):
        raise MeshError(f"{name}: the part is {ext[0]:.4g} x {ext[1]:.4g} x {ext[2]:.4g} mm, larger than the "
                        f"workspace {room[0]:.4g} x {room[1]:.4g} x {room[2]:.4g} mm; check the units (--units)")
    if not (layer_mm > 0 and np.isfinite(layer_mm)):
        raise MeshError(f"{name}: layer height {layer_mm!r} mm is not a positive number")
    layers = int(ext[2] / layer_mm) + 1
    if layers > MAX_LAYERS:
        raise MeshError(f"{name}: {layers} layers of {layer_mm:g} mm, over the limit of {MAX_LAYERS}")
    zmin, zmax = z_range if z_range is not None else face_z_range(v, faces)
    segs = int(np.sum(np.floor((zmax - zmin) / layer_mm) + 1))
    if segs > MAX_SEGMENTS:
        raise MeshError(f"{name}: slicing would make about {segs} segments, over the limit of {MAX_SEGMENTS}; "
                        "decimate the mesh or use thicker layers")

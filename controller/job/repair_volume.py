"""Repair volume (Padathu 2005's workflow, docs/contract.md §4 "Repair"): nominal CAD − stock (+ allowance).

manifold3d does the boolean operations (exact, always manifold). The result stays in the CAD frame:
the repair is planned there (`--frame cad`) and carried to the machine by the job's alignment.
The finishing allowance is added on top of the repaired region only: the missing volume is swept
up by the allowance (and the stock taken away again), so the repaired surface gets that much extra
metal to machine off while the intact faces of the stock get none.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from core.errors import InputError, MeshError

if TYPE_CHECKING:  # both are imported on first use: loading them costs the CLI's start-up
    import manifold3d
    import trimesh

_MIN_VOLUME_MM3 = 1e-3


@dataclass(frozen=True)
class RepairVolume:
    mesh: object                # trimesh.Trimesh in the CAD frame
    volume_mm3: float
    bounds: np.ndarray          # (2, 3)
    sticking_out_mm3: float     # stock outside the CAD (+ allowance): 0 for a valid stock


def to_manifold(mesh: trimesh.Trimesh, name: str) -> manifold3d.Manifold:
    # lazy: manifold3d loads only when this path runs (start-up time)
    import manifold3d

    m = manifold3d.Manifold(manifold3d.Mesh(vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
                                            tri_verts=np.asarray(mesh.faces, dtype=np.uint32)))
    if m.status() != manifold3d.Error.NoError or m.is_empty():
        raise MeshError(f"{name}: not a closed solid ({m.status().name}); repair the mesh and try again")
    return m


def to_trimesh(m: manifold3d.Manifold) -> trimesh.Trimesh:
    # lazy: trimesh loads only when this path runs (start-up time)
    import trimesh

    mm = m.to_mesh()
    return trimesh.Trimesh(np.asarray(mm.vert_properties, dtype=float)[:, :3], np.asarray(mm.tri_verts), process=True)


def repair_volume(cad: trimesh.Trimesh, stock: trimesh.Trimesh, allowance_mm: float = 0.0, *, cad_name: str = "CAD", stock_name: str = "stock",
                  tolerance_mm3: float = 1.0) -> RepairVolume:
    """CAD (swept up by the allowance) minus the stock; errors when the stock sticks out or nothing is missing."""
    if not (allowance_mm >= 0 and np.isfinite(allowance_mm)):
        raise InputError(f"--allowance: must be ≥ 0 mm, got {allowance_mm}")
    c = to_manifold(cad, cad_name)
    s = to_manifold(stock, stock_name)
    out = s - c
    sticking = float(out.volume())
    if sticking > tolerance_mm3:
        b = np.asarray(out.bounding_box()).reshape(2, 3)
        raise InputError(f"{stock_name}: the stock sticks out of the CAD by {sticking:.1f} mm³ (between "
                         f"{np.round(b[0], 2).tolist()} and {np.round(b[1], 2).tolist()} mm): check that both "
                         "are in the same frame and units, or machine the stock down first")
    rep = c - s
    if allowance_mm > 0 and rep.volume() > _MIN_VOLUME_MM3:
        rep = (rep + rep.translate((0.0, 0.0, float(allowance_mm)))) - s
    vol = float(rep.volume())
    if vol < max(tolerance_mm3, _MIN_VOLUME_MM3):
        raise InputError(f"nothing to repair: the stock {stock_name} fills the CAD {cad_name} "
                         f"(missing volume {vol:.3f} mm³)")
    return RepairVolume(to_trimesh(rep), vol, np.asarray(rep.bounding_box()).reshape(2, 3), sticking)

"""Repair volume (Padathu 2005's workflow, docs/contract.md §4 "Repair"): nominal CAD − stock (+ allowance).

manifold3d does the boolean operations (exact, always manifold). The result stays in the CAD frame:
the repair is planned there (`--frame cad`) and carried to the machine by the job's alignment.
The finishing allowance is added on top of the repaired region only: the missing volume is swept
up by the allowance (and the stock taken away again), so the repaired surface gets that much extra
metal to machine off while the intact faces of the stock get none.

Where the repaired region reaches the part's free edge (a side face of the CAD), the volume is also
carried `overhang_mm` beyond it (docs/repair.md "Free edges"): a bead laid up to an edge slumps
there, so the deposit is planned to hang over the edge by half a bead and machined back to CAD.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from controller.job.model import CellJob
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
    overhang_mm3: float = 0.0   # planned beyond the CAD's free edges (its outline), to be machined back


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


def _outward_steps(cad: manifold3d.Manifold, rep: manifold3d.Manifold, overhang_mm: float) -> list[tuple[float, float]]:
    """The xy moves that carry the repair beyond the CAD's outline: along the outward normal of each
    outline edge the repair's footprint runs along, and at each outline corner it covers along the
    sum of its two edges' normals (the corner's square); none along an edge it keeps off."""
    # lazy: shapely loads only when this path runs (start-up time)
    from shapely.geometry import LineString, Point, Polygon
    from shapely.ops import unary_union

    area = unary_union([Polygon(q) for q in rep.project().to_polygons() if len(q) >= 3]).buffer(1e-3)
    steps: set[tuple[float, float]] = set()
    for ring in cad.project().to_polygons():
        q = np.asarray(ring, dtype=float)
        if len(q) < 3:
            continue
        ccw = Polygon(q).exterior.is_ccw
        e = np.roll(q, -1, axis=0) - q
        n = np.column_stack([e[:, 1], -e[:, 0]]) * (1.0 if ccw else -1.0)   # outward (holes: into the hole)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        runs = [area.intersection(LineString([q[i], q[i] + e[i]])).length > 0.5 for i in range(len(q))]
        for i in range(len(q)):
            if runs[i]:
                steps.add(tuple(np.round(n[i] * overhang_mm, 4)))
            if runs[i] and runs[i - 1] and area.contains(Point(q[i])):
                steps.add(tuple(np.round((n[i] + n[i - 1]) * overhang_mm, 4)))
    return sorted(steps)


def beyond_edges(rep: manifold3d.Manifold, cad: manifold3d.Manifold, stock: manifold3d.Manifold,
                 overhang_mm: float, sweep: int = 8) -> manifold3d.Manifold:
    """The repair volume carried `overhang_mm` beyond the CAD's outline where it reaches a free edge
    (`_outward_steps`): the volume swept out (`sweep` steps), less the CAD's footprint prism (nothing lands on the
    intact top) and the stock; empty where the region keeps off the edges."""
    # lazy: manifold3d loads only when this path runs (start-up time)
    import manifold3d

    steps = _outward_steps(cad, rep, overhang_mm)
    if not steps:
        return manifold3d.Manifold()
    lo, hi = np.asarray(rep.bounding_box()).reshape(2, 3)
    clo, chi = np.asarray(cad.bounding_box()).reshape(2, 3)
    z0, z1 = float(min(lo[2], clo[2])) - 1.0, float(max(hi[2], chi[2])) + 1.0
    column = manifold3d.Manifold.extrude(cad.project(), z1 - z0).translate((0.0, 0.0, z0))
    # swept, not moved: beyond the edge the repair keeps its cross-section at the edge (a ramp's too)
    grown = manifold3d.Manifold.batch_boolean([rep.translate((dx * f, dy * f, 0.0)) for dx, dy in steps
                                               for f in np.linspace(1.0 / sweep, 1.0, sweep)], manifold3d.OpType.Add)
    out: manifold3d.Manifold = grown - column - stock
    return out


def repair_volume(cad: trimesh.Trimesh, stock: trimesh.Trimesh, allowance_mm: float = 0.0, *, cad_name: str = "CAD", stock_name: str = "stock",
                  tolerance_mm3: float = 1.0, overhang_mm: float = 0.0) -> RepairVolume:
    """CAD (swept up by the allowance) minus the stock, carried `overhang_mm` beyond the CAD's free
    edges; errors when the stock sticks out or nothing is missing."""
    if not (allowance_mm >= 0 and np.isfinite(allowance_mm)):
        raise InputError(f"--allowance: must be ≥ 0 mm, got {allowance_mm}")
    if not (overhang_mm >= 0 and np.isfinite(overhang_mm)):
        raise InputError(f"--overhang: must be ≥ 0 mm, got {overhang_mm}")
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
    hang = 0.0
    if overhang_mm > 0:
        over = beyond_edges(rep, c, s, float(overhang_mm))
        hang = float(over.volume())
        if hang > _MIN_VOLUME_MM3:
            rep = rep + over
            vol = float(rep.volume())
    return RepairVolume(to_trimesh(rep), vol, np.asarray(rep.bounding_box()).reshape(2, 3), sticking, hang)


def load_cad(job: CellJob, job_path: Path | None, which: str = "cad") -> trimesh.Trimesh:
    """A repair job's CAD (or, `which="stock"`, its stock) mesh, a relative path looked up next to the job
    (controller/repair.py, `cell finish`)."""
    # lazy: trimesh loads only when this path runs (start-up time)
    import trimesh

    cad = (job.repair.cad if which == "cad" else job.repair.stock) if job.repair is not None else None
    if not cad:
        raise InputError(f"job: not a repair job (no repair.{which}); plan it with `cell repair plan`")
    p = Path(cad)
    if not p.is_absolute() and job_path is not None and (job_path.parent / p).is_file():
        p = job_path.parent / p   # a relative CAD is relative to the job file's directory
    if not p.is_file():
        where = f" (looked in {job_path.parent.resolve()})" if job_path is not None and not Path(cad).is_absolute() else ""
        raise InputError(f"job repair.{which} {cad}: no such file{where}; plan the repair again or put the mesh there")
    return trimesh.load_mesh(str(p), force="mesh")

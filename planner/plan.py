"""The planning pipeline: mesh → slices → islands → perimeters, infill, gap beads → ordered Job."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import shapely

from planner.bead import step_over
from planner.errors import EnvelopeError, InputError, MeshError
from planner.gapfill import centre_lines
from planner.infill import scan_fill
from planner.job import BeadInfo, Interpass, Job, Layer, Pass, Source
from planner.material import Material
from planner.mesh import PreparedMesh, check_size, prepare_mesh, read_mesh
from planner.ordering import join_chains, link_into_loops, order_passes, seam_at
from planner.path2d import Path2D
from planner.perimeters import perimeter_loops, split_thin
from planner.process import ProcessPoint, inverse
from planner.regions import islands, polygons_of
from planner.slicer import LayerSlice, slice_levels, slice_mesh
from planner.summary import ARC_START_S, TRAVEL_MM_MIN, LayerQuality, layer_quality, summarise

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class PlanOptions:
    width_mm: float
    layer_height_mm: float | None = None  # default: the bead height of the process model
    perimeters: int | str | None = 2  # None or "all": offset until the loops meet
    units: str = "mm"
    allow_outside: bool = False  # accept welding points outside the material's envelope
    infill_angle_deg: float = 0.0  # scan direction of layer 0; +90° every layer

    def __post_init__(self) -> None:
        if isinstance(self.perimeters, str):  # "all" or "3", as on the command line
            p = self.perimeters.strip().lower()
            if p != "all" and not p.isdigit():
                raise InputError(f"--perimeters: '{self.perimeters}' is not a number of perimeters or 'all'")
            object.__setattr__(self, "perimeters", None if p == "all" else int(p))
        if not (self.width_mm > 0 and np.isfinite(self.width_mm)):
            raise InputError(f"--width: must be a positive number of mm, got {self.width_mm}")
        if self.layer_height_mm is not None and not (0 < self.layer_height_mm < self.width_mm * 5):
            raise InputError(f"--layer-height: must be > 0 mm and sensible for a {self.width_mm} mm bead, "
                             f"got {self.layer_height_mm}")
        if self.perimeters is not None and not (0 <= self.perimeters <= 1000):
            raise InputError(f"--perimeters: must be 0..1000 or 'all', got {self.perimeters}")


class _Process:
    """Welding points per bead width at the layer height, cached."""

    def __init__(self, material: Material, height: float, allow_outside: bool, nominal: float):
        self.material, self.height, self.allow, self.nominal = material, height, allow_outside, nominal
        self.cache: dict[float, ProcessPoint] = {}

    def point(self, width: float) -> ProcessPoint:
        w = round(float(width), 3)
        if w not in self.cache:
            self.cache[w] = self._solve(w)
        return self.cache[w]

    def _solve(self, w: float) -> ProcessPoint:
        try:
            return inverse(self.material, w, self.height, allow_outside=self.allow)
        except EnvelopeError:
            if w == round(self.nominal, 3):
                raise
        # A gap bead whose width the envelope cannot weld: the nearest weldable width toward nominal.
        for cand in np.linspace(w, self.nominal, 9)[1:]:
            try:
                return inverse(self.material, round(float(cand), 3), self.height)
            except EnvelopeError:
                continue
        return inverse(self.material, self.nominal, self.height, allow_outside=self.allow)


def plan_part(mesh_or_path, options: PlanOptions,
              material: Material, progress: Progress | None = None) -> Job:
    """Plan a part (a path, a trimesh.Trimesh or a PreparedMesh) into a `cell-job/1` Job.

    Deterministic: the same input gives the same job, byte for byte once serialised.
    """
    mesh = _mesh(mesh_or_path, options.units)
    w = options.width_mm
    nominal = inverse(material, w, options.layer_height_mm, allow_outside=options.allow_outside)
    height = options.layer_height_mm or nominal.height_mm
    check_size(mesh, w, height)
    step = step_over(w, overlap_model=material.bead.overlap_model, profile=material.bead.profile)
    proc = _Process(material, height, options.allow_outside, w)
    levels = slice_levels(float(mesh.extents[2]), height)
    gap_tols = (1e-6, 0.01 * w, 0.1 * w, 0.5 * w)
    slices = slice_mesh(mesh.vertices, mesh.faces, mesh.face_normals, levels, gap_tols)
    _fail_on_open(slices, mesh.source.file, w)
    layers: list[Layer] = []
    qualities: list[LayerQuality] = []
    pos = np.zeros(2)
    time_s = 0.0
    n_passes = 0
    interpass = Interpass(material.interpass.max_temperature_c, material.interpass.dwell_s)
    for sl in slices:
        region, paths, pos, travel, stats = _plan_layer(sl, w, step, options, pos)
        paths = [_as_welded(p, proc) for p in paths]
        q = layer_quality(region, paths, w, height)
        qualities.append(q)
        z = float((sl.index + 1) * height)
        passes = _passes(paths, sl, z, proc)
        n_passes += len(passes)
        time_s += travel / TRAVEL_MM_MIN * 60.0 + len(passes) * ARC_START_S
        time_s += sum(p.length_mm / p.speed_mm_min * 60.0 for p in passes)
        if sl.index > 0:
            time_s += material.interpass.dwell_s
        layers.append(Layer(sl.index, z, height, tuple(passes), interpass,
                            {"area_mm2": round(q.area_mm2, 2), "coverage": round(q.coverage, 5),
                             "perimeter_loops": stats["loops"], "fill_regions": stats["regions"]}))
        if progress is not None:
            progress(sl.index + 1, len(slices))
    summary = summarise(qualities, n_passes, time_s)
    summary["repairs"] = list(mesh.repairs)
    summary["open_contours"] = []
    summary["closed_gaps"] = sum(1 for sl in slices for c in sl.contours if c.gap_mm > 1e-6)
    mat = material.model_dump(mode="json")
    bead = BeadInfo(w, height, step, f"{material.bead.profile}/{material.bead.overlap_model}")
    src = Source(mesh.source.file, mesh.source.sha256, mesh.source.units)
    return Job(src, mat, bead, tuple(layers), summary)


def _mesh(m, units: str) -> PreparedMesh:
    if isinstance(m, PreparedMesh):
        return m
    if hasattr(m, "faces") and hasattr(m, "vertices"):  # a trimesh.Trimesh
        return prepare_mesh(m, units)
    return read_mesh(m, units)


def _fail_on_open(slices: list[LayerSlice], name: str, w: float) -> None:
    """Contours the gap tolerances could not close are listed, never dropped."""
    bad = [(sl, c) for sl in slices for c in sl.open_contours]
    if not bad:
        return
    lines = []
    for sl, c in bad[:8]:
        a, b = c.points[0], c.points[-1]
        lines.append(f"layer {sl.index} (z {sl.z_mm:.2f} mm): open from ({a[0]:.2f}, {a[1]:.2f}) to "
                     f"({b[0]:.2f}, {b[1]:.2f}), gap {np.hypot(*(b - a)):.2f} mm")
    more = f"; and {len(bad) - 8} more" if len(bad) > 8 else ""
    raise MeshError(f"{name}: {len(bad)} open contour(s) wider than the gap tolerance ({0.5 * w:g} mm): "
                    + "; ".join(lines) + more + "; close the mesh (e.g. in a mesh repair tool) and plan again")


def _plan_layer(sl: LayerSlice, w: float, step: float, opt: PlanOptions, pos: np.ndarray):
    """Islands of one layer → ordered Path2D beads; returns (layer region, paths, end, travel)."""
    polys = islands([c.points for c in sl.contours if c.closed], simplify_mm=0.005 * w)
    region = shapely.union_all(polys) if polys else shapely.Polygon()
    angle = opt.infill_angle_deg + 90.0 * (sl.index % 2)
    per_island = []
    stats = {"loops": 0, "regions": 0}
    for poly in polys:
        thick, thin = split_thin(poly, w)
        groups: list[list[Path2D]] = [[], [], []]
        for t in thick:
            if opt.perimeters == 0:
                loops, inset = [], 0.5 * w - step  # infill centres from half a bead inside
            else:
                loops, inset = perimeter_loops(t, w, step, opt.perimeters)
            stats["loops"] += sum(len(lv) for lv in loops)
            if loops or opt.perimeters == 0:
                infill_region = t.buffer(-(inset + 0.75 * step)) if opt.perimeters is not None else shapely.Polygon()
                stats["regions"] += len(polygons_of(infill_region))
                chains = scan_fill(infill_region, step, w, angle) if not infill_region.is_empty else []
                filled = list(chains)
                if len(chains) > 1:
                    chains = join_chains(chains, 2.5 * step, t.buffer(-inset + 0.1 * step))
                inner, chains = link_into_loops(loops[-1] if loops else [], chains, 2.0 * step)
                outer = [lp for lv in loops[:-1] for lp in lv]
                groups[0] += [seam_at(lp, sl.index) if lp.closed else lp for lp in outer + inner]
                groups[1] += chains
                # What neither the perimeters nor the scan lines reach gets centre-line gap beads.
                rest = t.buffer(-(inset + 0.5 * w))
                if filled and not rest.is_empty:
                    reach = shapely.buffer(np.array([shapely.linestrings(c.points) for c in filled], dtype=object),
                                           0.5 * w, quad_segs=4)
                    rest = rest.difference(shapely.union_all(reach))
            else:
                rest = t
            for piece in polygons_of(rest):
                if piece.area > 0.3 * w * w:
                    beads = centre_lines(piece, w, min_width=0.4 * w)
                    stats["regions"] += bool(beads)
                    groups[2] += beads
        for t in thin:
            beads = centre_lines(t, w)
            stats["regions"] += bool(beads)
            groups[2] += beads
        per_island.append(groups)
    ordered: list[Path2D] = []
    travel = 0.0
    todo = list(range(len(per_island)))
    while todo:
        # Next island: the one whose nearest bead end is closest to where the torch is.
        def near(i: int) -> float:
            ends = [p.points[k] for g in per_island[i] for p in g for k in (0, -1)]
            return min((float(np.hypot(*(e - pos))) for e in ends), default=np.inf)
        i = min(todo, key=near)
        todo.remove(i)
        seq, end = order_passes(per_island[i], pos)
        for p in seq:
            travel += float(np.hypot(*(p.points[0] - pos)))
            pos = p.points[-1]
        ordered += seq
        pos = end
    return region, ordered, pos, travel, stats


def _as_welded(p: Path2D, proc: _Process) -> Path2D:
    """The bead as the process will weld it: a gap bead may come out wider than its pocket."""
    w = proc.point(p.width_mm).width_mm
    if abs(w - p.width_mm) < 1e-9:
        return p
    return Path2D(p.role, p.points, w, p.closed, w if p.role == "gap" else p.share_mm)


def _passes(paths: list[Path2D], sl: LayerSlice, z: float, proc: _Process) -> list[Pass]:
    closed = [c for c in sl.contours if c.closed]
    cpts = np.vstack([c.points for c in closed]) if closed else None
    nrm = np.vstack([c.normals for c in closed]) if closed else None
    out = []
    for p in paths:
        pp = proc.point(p.width_mm)
        pts = np.column_stack([p.points, np.full(len(p.points), z)])
        normals = None
        if p.role == "perimeter" and cpts is not None:
            normals = nrm[_nearest(p.points, cpts)]
        out.append(Pass(p.role, pp.width_mm, pp.current_a, pp.speed_mm_min, pp.wfs_m_min, pts, normals))
    return out


def _nearest(q: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Index of the nearest contour point for each query point."""
    from scipy.spatial import cKDTree

    return cKDTree(pts).query(q)[1]

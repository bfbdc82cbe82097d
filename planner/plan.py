"""The planning pipeline: mesh → slices → islands → perimeters, infill, gap beads → ordered Job."""
from __future__ import annotations

import dataclasses
from collections import deque
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import shapely
from shapely.geometry import Polygon

from planner import limits
from core.errors import MeshError
from planner.balance import laid_area_mm2
from planner.bead import area_factor, step_over
from planner.ding import close_share
from planner.feedforward import Envelope, LayerLevel, level_summary
from planner.level_memo import LevelMemo
from planner import level_pour
from planner.job import BeadInfo, Interpass, Job, Layer, Pass, Source
from planner.ahead import Ahead, Done, Later, workers
from planner.processes import MIN_LAYERS, Processes
from planner.layer import LayerCtx, LayerPlan, placed, reseamed
from planner.nearnet import layer_count
from planner.overhang import overhang_limit_mm
from planner.mesh import PreparedMesh, check_size, prepare_mesh, read_mesh
from planner.process import inverse
from planner.path2d import Path2D
from planner.slicer import LayerSlice, face_z_range, slice_levels, slice_mesh
from planner.stubs import drop_short
from planner.summary import ARC_START_S, TRAVEL_MM_MIN, LayerQuality, layer_quality, summarise
from planner.thin import legal_widths
from planner.options import PlanOptions
from planner.verdict import Verdict
from planner.weld import CellLimits, Process, as_welded, weld_passes

if TYPE_CHECKING:  # annotations only: `cell plan` passes a remembered material (core.config_cache) and
    # never imports pydantic
    from core.material import Material

Progress = Callable[[int, int], None]

__all__ = ["PlanOptions", "Progress", "in_frame", "plan_part"]


def plan_part(mesh_or_path: Any, options: PlanOptions,
              material: Material, progress: Progress | None = None) -> Job:
    """Plan a part (a path, a trimesh.Trimesh or a PreparedMesh) into a Job (`cell-job/2` when the
    feed-forward gives passes per-segment speeds: planner/feedforward.py).

    Deterministic: the same input gives the same job, byte for byte once serialised. What cannot
    be planned (underfill, low coverage, overhangs) fails the plan naming the layers, unless allowed.
    """
    mesh = _mesh(mesh_or_path, options.units)
    w = options.width_mm
    nominal = inverse(material, w, options.layer_height_mm, allow_outside=options.allow_outside)
    height = options.layer_height_mm or nominal.height_mm
    check_size(mesh, w, height)
    z_range = face_z_range(mesh.vertices, mesh.faces)
    limits.check_before_slicing(mesh.source.file, mesh.vertices, mesh.faces, height, options.workspace_mm, z_range)
    run = _Run(options, material, height)
    top_z = float(mesh.extents[2])
    gap_tols = (1e-6, 0.01 * w, 0.1 * w, 0.5 * w)
    slices = slice_mesh(mesh.vertices, mesh.faces, mesh.face_normals, slice_levels(top_z, height), gap_tols, z_range)
    del z_range
    _fail_on_open(slices, mesh.source.file, w)
    n_net = len(slices)
    slices = _with_top(slices, layer_count(top_z, height, run.ctx.allowance, n_net), height)
    layers: list[Layer] = []
    tops = [sl.index >= n_net for sl in slices]
    with _levelling(run, len(slices)) as procs, Ahead(slices, tops, run.ctx, _LayerMemo.key, _LayerMemo.misses) as ahead:
        # each layer started in turn (its beads ordered from where the torch is), welded and judged
        # a few layers behind (its quality computed meanwhile on a thread), levelled on a worker
        # process and finished a few layers behind that; an error is raised at its own layer, in
        # order, as if the layers were planned one by one
        run.procs = procs
        started: deque[_Started | BaseException] = deque()
        welded: deque[_Welded] = deque()
        for sl, top in zip(slices, tops):
            started.append(_started(run, sl, top, ahead))
            while started and (len(started) > ahead.depth or isinstance(started[-1], BaseException)):
                welded.append(_welded(run, started.popleft()))
                while len(welded) > 2 * procs.n:
                    layers.append(_finished(run, welded.popleft(), progress, len(slices)))
        while started:
            welded.append(_welded(run, started.popleft()))
        while welded:
            layers.append(_finished(run, welded.popleft(), progress, len(slices)))
    summary = summarise(run.qualities, run.n_passes, run.time_s)
    summary["arc_time_s"] = round(run.arc_time_s, 1)
    summary.update(run.verdict.finish(mesh.source.file, run.qualities))
    summary["machining"] = _machining(run.ctx.allowance, run.qualities, len(slices) * height - top_z, len(slices) - n_net)
    summary["repairs"] = list(mesh.repairs)
    summary["open_contours"] = []
    summary["closed_gaps"] = sum(1 for sl in slices for c in sl.contours if c.gap_mm > 1e-6)
    if options.feed_forward:
        summary["feed_forward"] = level_summary(run.levels)
    mat = material.model_dump(mode="json")
    bead = BeadInfo(w, height, run.ctx.step, f"{material.bead.profile}/{material.bead.overlap_model}")
    src = Source(mesh.source.file, mesh.source.sha256, mesh.source.units)
    job = Job(src, mat, bead, tuple(layers), summary)
    if options.five_axis is not None:  # the tool tilts to bring the overhangs within the rule
        # a 5-axis plan only: a 3-axis plan's start-up does not load it (issue 28)
        from planner import five_axis

        fa = dataclasses.replace(options.five_axis, max_overhang_deg=material.max_overhang_deg)
        job = five_axis.apply(job, fa, options.allow_overhang, run.regions)
    return in_frame(job, options.frame, mesh.z_shift_mm)


class _Run:
    """One plan's state carried from layer to layer: the torch position, the verdict, the totals."""

    def __init__(self, options: PlanOptions, material: Material, height: float) -> None:
        w = options.width_mm
        step = step_over(w, overlap_model=material.bead.overlap_model, profile=material.bead.profile)
        perimeters = options.perimeters if not isinstance(options.perimeters, str) else None
        self.ctx = LayerCtx(w, step, perimeters, options.infill_angle_deg,
                            legal_widths(material, height, w, step / w, options.allow_outside),
                            area_factor(material.bead.profile), material.min_bead_length_mm or 2.0 * w,
                            _allowance(options, material), options.min_coverage, height,
                            _min_share(material, options.cell_limits, height), _support(options, material, height))
        self.options, self.material, self.height = options, material, height
        self.proc = Process(material, height, options.allow_outside, w)
        self.verdict = Verdict(options, material, self.ctx)
        self.interpass = Interpass(material.interpass.max_temperature_c, material.interpass.dwell_s)
        self.memo = _LayerMemo()
        self.pos = np.zeros(2)
        self.below: shapely.Geometry | None = None
        self.regions: list[shapely.Geometry] = []  # each layer's outline, for the 5-axis overhang rule
        self.qualities: list[LayerQuality] = []
        self.time_s = 0.0
        self.arc_time_s = 0.0  # the beads alone, at their planned speed (the record compares it)
        self.n_passes = 0
        lim, r = options.cell_limits, material.ribeiro
        self.envelope = Envelope(lim.min_speed_mm_min, lim.max_speed_mm_min,
                                 *((0.05, lim.source_wfs_max_m_min) if options.allow_outside else (r.wfs_min_m_min, r.wfs_max_m_min)))
        self.levels: list[LayerLevel] = []   # the feed-forward's predicted top spread per layer
        self.law = level_pour.BeadLaw(r.k1, r.k2, r.k3, r.i_min_a, r.i_max_a, r.wfs_min_m_min, r.wfs_max_m_min)
        self.stack: level_pour.Stack | None = None   # the poured feed-forward's predicted stack
        self.procs = Processes(0)   # where the feed-forward levels a layer (plan_part sets it)
        self.level_memo = LevelMemo()

    def start(self, sl: LayerSlice, top: bool, ahead: Ahead) -> _Started:
        """The layer's beads ordered from where the torch is (the memo's when a layer below had the
        same islands), and their quality and Ding check underway; the torch moves on."""
        net, _, key = ahead.prepared[sl.index]
        hit = self.memo.get(key, sl.index, self.pos, self.proc)
        if hit is not None:
            lp, paths, judged = hit
        else:
            lp = placed(ahead.groups(sl.index), self.pos)
            paths = [as_welded(p, self.proc) for p in lp.paths]
            stock_of = net if self.ctx.allowance > 0 and not top and net else None
            judged = ahead.later(self._judge, lp.region, paths, stock_of)
            self.memo.put(key, lp, judged)
        self.pos = lp.end
        return sl, lp, paths, judged

    def _judge(self, region: shapely.Geometry, paths: list[Path2D], net: list[Polygon] | None) -> tuple[LayerQuality, float]:
        """The layer's coverage, metal and stock (planner.summary) and its Ding check (planner.ding)."""
        w = self.ctx.width
        q = layer_quality(region, paths, w, self.height, shapely.union_all(net) if net else None)
        return q, close_share(paths, self.material.bead.min_step_over_ratio, w)

    def layer(self, started: _Started) -> _Welded:
        """Weld and judge one layer, in turn; its levelling under way."""
        sl, lp, paths, judged = started
        q, close = judged.result()
        v, h = self.verdict, self.height
        paths = drop_short(paths, self.ctx.min_length, sl.index, v.stubs)
        v.ding(sl.index, close)
        self.qualities.append(q)
        v.layer(sl.index, lp, q, self.below, h)
        self.below = lp.region
        self.regions.append(lp.region)
        z = float((sl.index + 1) * h)
        passes, worst, adjusted = weld_passes(paths, sl, z, self.proc, self.options.cell_limits, v.limits)
        v.balance(worst)
        v.wfs_adjusted += adjusted
        if q.area_mm2 > 0 and passes:  # the layer's metal against its section x h (docs/contract.md §3.7)
            laid = sum(laid_area_mm2(self.material.wire_diameter_mm, p.wfs_m_min, p.speed_mm_min) * p.length_mm
                       for p in passes)
            v.layer_balance(abs(laid - q.area_mm2 * h) / (q.area_mm2 * h))
        # each bead's metal kept, its spread along the path levelled; not on a 5-axis plan (its beads
        # lean: the tool axes come after, from the passes as the walls give them, planner/five_axis.py)
        levelling: Later[tuple[tuple[Pass, ...], LayerLevel]] | None = None
        if self.options.feed_forward and self.options.five_axis is None:
            if self.options.feed_forward_pour:   # on the stack of the layers below: in turn
                if self.stack is None:
                    self.stack = level_pour.Stack(level_pour.CELL_MM, z - h)
                levelling = Done(level_pour.level_layer(tuple(passes), self.material.wire_diameter_mm, self.envelope,
                                                        self.law, self.stack))
            else:   # this layer's passes alone: on a worker process (planner/processes.py)
                # (or a layer levelled before with the same inputs: planner/level_memo.py)
                levelling = self.level_memo.level(self.procs.submit, tuple(passes), self.material.wire_diameter_mm,
                                                  self.envelope)
        return sl, z, lp, q, passes, levelling

    def finish(self, welded: _Welded) -> Layer:
        """The layer's levelled passes and its time, in turn."""
        sl, z, lp, q, passes, levelling = welded
        h = self.height
        if levelling is not None:
            levelled, lvl = levelling.result()
            passes = list(levelled)
            self.levels.append(lvl)
        self.n_passes += len(passes)
        arc_s = sum(p.arc_time_s for p in passes)   # each segment at its own speed
        self.time_s += lp.travel_mm / TRAVEL_MM_MIN * 60.0 + len(passes) * ARC_START_S + arc_s
        self.arc_time_s += arc_s
        if sl.index > 0:
            self.time_s += self.material.interpass.dwell_s
        return Layer(sl.index, z, h, tuple(passes), self.interpass,
                     {"area_mm2": round(q.area_mm2, 2), "coverage": round(q.coverage, 5),
                      "perimeter_loops": lp.stats["loops"], "fill_regions": lp.stats["regions"]})


_Started = tuple[LayerSlice, LayerPlan, list[Path2D], "Later[tuple[LayerQuality, float]]"]
_Welded = tuple[LayerSlice, float, LayerPlan, LayerQuality, list[Pass], "Later[tuple[tuple[Pass, ...], LayerLevel]] | None"]


def _levelling(run: _Run, n_layers: int) -> Processes:
    """Worker processes for the feed-forward's per-layer levelling, when the plan has enough layers to level."""
    o = run.options
    on = o.feed_forward and o.five_axis is None and not o.feed_forward_pour and n_layers >= MIN_LAYERS
    return Processes(workers() if on else 0)


def _started(run: _Run, sl: LayerSlice, top: bool, ahead: Ahead) -> _Started | BaseException:
    try:
        return run.start(sl, top, ahead)
    except Exception as exc:  # raised in turn, once the layers below are done (see plan_part)
        return exc


def _welded(run: _Run, started: _Started | BaseException) -> _Welded:
    if isinstance(started, BaseException):
        raise started
    return run.layer(started)


def _finished(run: _Run, welded: _Welded, progress: Progress | None, total: int) -> Layer:
    layer = run.finish(welded)
    if progress is not None:
        progress(layer.index + 1, total)
    return layer


def in_frame(job: Job, frame: str, z_shift_mm: float) -> Job:
    """The job in its frame: `cad` puts back the height the mesh intake took off (z = 0 → CAD z)."""
    if frame != "cad":
        return job
    layers = tuple(dataclasses.replace(L, z_mm=L.z_mm + z_shift_mm, passes=tuple(
        dataclasses.replace(p, points=p.points + [0.0, 0.0, z_shift_mm]) for p in L.passes)) for L in job.layers)
    return dataclasses.replace(job, layers=layers, frame="cad")


class _LayerMemo:
    """A layer whose islands repeat those of a layer below with the same scan direction (a prism)
    is planned the same; its seams move on and its beads are ordered from where the torch is."""

    def __init__(self) -> None:
        self.seen: dict[tuple[bytes, int, bool], tuple[LayerPlan, Later[tuple[LayerQuality, float]]]] = {}

    BOUND = 64  # layers kept: a prism repeats the layer just below

    @staticmethod
    def key(polys: list[Polygon], index: int, tag: bool) -> tuple[bytes, int, bool]:
        norm = shapely.normalize(shapely.set_precision(np.asarray(polys, dtype=object), 1e-6))
        return (b"".join(shapely.to_wkb(norm).tolist()), index % 2, tag)

    @classmethod
    def misses(cls, keys: list[tuple[bytes, int, bool]]) -> list[bool]:
        """Which layers get() will not have, layer after layer (get, then put on a miss, as below)."""
        seen: set[tuple[bytes, int, bool]] = set()
        out = []
        for k in keys:
            out.append(k not in seen)
            if out[-1]:
                if len(seen) >= cls.BOUND:
                    seen.clear()
                seen.add(k)
        return out

    def get(self, key: tuple[bytes, int, bool], index: int, pos: np.ndarray,
            proc: Process) -> tuple[LayerPlan, list[Path2D], Later[tuple[LayerQuality, float]]] | None:
        hit = self.seen.get(key)
        if hit is None:
            return None
        lp, judged = hit
        lp = reseamed(lp, index, pos)
        return lp, [as_welded(p, proc) for p in lp.paths], judged

    def put(self, key: tuple[bytes, int, bool], lp: LayerPlan, judged: Later[tuple[LayerQuality, float]]) -> None:
        if len(self.seen) >= self.BOUND:
            self.seen.clear()
        self.seen[key] = (lp, judged)


def _min_share(material: Material, lim: CellLimits, height: float) -> float:
    """The narrowest strip (mm) a bead can fill inside the cell's limits and the envelope: the wire at
    the material's least feed over the cell's max speed, per layer height (docs/contract.md §3.10)."""
    wire = np.pi * material.wire_diameter_mm ** 2 / 4.0
    return float(wire * material.ribeiro.wfs_min_m_min * 1000.0 / lim.max_speed_mm_min / height)


def _support(options: PlanOptions, material: Material, height: float) -> float:
    """Near-net on 3 axes: the step out per layer the stock under an overhang is filled to (nine
    tenths of the overhang rule's, planner.overhang); 0 for a net or a 5-axis plan (it tilts instead)."""
    if _allowance(options, material) <= 0.0 or options.five_axis is not None:
        return 0.0
    return 0.9 * overhang_limit_mm(height, options.width_mm, material.max_overhang_deg)


def _allowance(options: PlanOptions, material: Material) -> float:
    """The machining allowance: the option's, else the material's, else 0 (net shape)."""
    if options.machining_allowance_mm is not None:
        return float(options.machining_allowance_mm)
    return float(material.machining_allowance_mm or 0.0)


def _with_top(slices: list[LayerSlice], count: int, height: float) -> list[LayerSlice]:
    """The slices, and layers repeating the top one's contours up to `count` (the top's stock)."""
    if count <= len(slices) or not slices:
        return slices
    top = slices[-1]
    return slices + [LayerSlice(i, (i + 0.5) * height, top.contours) for i in range(len(slices), count)]


def _machining(allowance: float, qualities: list[LayerQuality], top_mm: float, added: int) -> dict[str, Any]:
    """The summary's near-net record: allowance, stock left to machine per face, layers added on top."""
    out: dict[str, Any] = {"allowance_mm": round(allowance, 3)}
    if allowance <= 0:
        return out
    st = [q.stock for q in qualities if q.stock is not None]
    out["stock_mm"] = {"side_min": round(min((s[0] for s in st), default=0.0), 3),
                       "side_max": round(max((s[1] for s in st), default=0.0), 3),
                       "top": round(top_mm, 3), "bottom": 0.0}
    out["top_layers_added"] = added
    return out


def _mesh(m: Any, units: str) -> PreparedMesh:
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

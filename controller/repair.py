"""`cell repair run`: probe, level, face angle, transform, deposit, probe again, report (issue 17).

Padathu 2005's workflow on one connected cell, in one session, so the alignment the build uses
was probed after the CNC's last homing/reset (the executor refuses an older one):
1. the alignment routine (top grid → A/B leveling, side face → face angle; CAD rotated to match),
   with its touches kept clear of the repair region;
2. the repair job (CAD frame) moved by that transform; the job records it (one alignment);
3. the build: the executor commands the leveling, checks it and deposits;
4. verify: a grid of probe touches over the repaired region, read back into the CAD frame, against
   the planned top and against CAD + allowance.
"""
from __future__ import annotations

import asyncio
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Awaitable, Callable

import numpy as np

from controller.align.intact import MIN_SIDE_MM, intact_spots
from controller.align.surface_probe import flood_spots, probe_cad_points, refine_spots, repaired_spots, scan_settings, stock_spots
from controller.motion.mill import change_tool, program_lines, run_program
from controller.align.routine import AlignResult, ProbePlan, alignment_record, plan_for_mesh
from controller.api import CellController
from controller.job.model import CellJob
from controller.job.redeposit import redeposit_job
from controller.job.repair_volume import load_cad
from controller.motion.cnc5 import refuse_unfed
from controller.motion.kinematics import Trunnion, apply_to_job
from controller.runtime import stops
from controller.ports import CncLinkPort
from core.config import CellConfig
from core.errors import CellError, Fault, InputError
from planner.dropcutter import ToolShape
from planner.finish import Cut, FinishPlan, cad_top, plan_finish, stock_above_cad, stock_margin, stock_surface
from planner.job import Layer

if TYPE_CHECKING:   # untyped libraries, loaded lazily at run time (start-up time)
    import trimesh
    from shapely.geometry.base import BaseGeometry


@dataclass(frozen=True)
class VerifyResult:
    points_cad: np.ndarray        # (n, 3) probed, CAD frame
    planned_top_mm: float         # the highest planned layer
    nominal_top_mm: float         # CAD + allowance
    tolerance_mm: float
    planned_z: np.ndarray | None = None   # (n,) the planned top under each touch (None: planned_top_mm)
    kinds: tuple[str, ...] = ()           # per touch: "inside" or "edge"

    def as_dict(self) -> dict[str, Any]:
        z = self.points_cad[:, 2]
        planned = self.planned_z if self.planned_z is not None else np.full(len(z), self.planned_top_mm)
        err = z - planned
        nom = z - np.minimum(self.nominal_top_mm, planned + self.tolerance_mm)
        flat = float(err.max() - err.min())  # peak to valley against the planned top under each touch
        defects = []
        if float(np.abs(err).max()) > self.tolerance_mm:
            k = int(np.argmax(np.abs(err)))
            defects.append({"kind": "height", "at": np.round(self.points_cad[k], 3).tolist(),
                            "error_mm": round(float(err[k]), 4)})
        if float(nom.min()) < -self.tolerance_mm:
            k = int(np.argmin(nom))
            defects.append({"kind": "below CAD + allowance", "at": np.round(self.points_cad[k], 3).tolist(),
                            "error_mm": round(float(nom[k]), 4)})
        return {"points": len(z), "planned_top_mm": round(self.planned_top_mm, 4),
                "nominal_top_mm": round(self.nominal_top_mm, 4),
                "height_error_mean_mm": round(float(err.mean()), 4),
                "height_error_max_mm": round(float(np.abs(err).max()), 4),
                "vs_nominal_mean_mm": round(float(nom.mean()), 4), "vs_nominal_min_mm": round(float(nom.min()), 4),
                "flatness_mm": round(flat, 4), "tolerance_mm": self.tolerance_mm, "defects": defects,
                "edge_points": sum(1 for k in self.kinds if k == "edge"),
                "at": np.round(self.points_cad, 3).tolist()}


def probe_plan(cad: "trimesh.Trimesh", job: CellJob) -> ProbePlan:
    """The alignment's touches on the CAD, on the intact faces off the repair region and its
    keep-out (controller/align/intact.py): refused only when too little intact face is left."""
    lo, hi = np.asarray(cad.bounds, dtype=float)
    rb = job.repair.bounds_mm if job.repair is not None and job.repair.bounds_mm is not None else None
    if rb is None:   # no region: the routine's own grid
        return plan_for_mesh(cad)
    depth = min(5.0, (hi[2] - lo[2]) / 2)   # plan_for_mesh's side touches: this far under the top
    spots = intact_spots(np.asarray(cad.triangles, dtype=float), np.asarray(rb, dtype=float), face_z=hi[2] - depth)
    a, b = spots.side_y
    half = min(b - a, max(hi[1] - lo[1] - 20.0, MIN_SIDE_MM)) / 2   # the row at most the face less 10 mm a side
    mid = (a + b) / 2
    return plan_for_mesh(cad, top_xy=spots.top_xy, side_y=np.linspace(mid - half, mid + half, 5),
                         tertiary_x=spots.tertiary_x)


def _layer_footprint(L: Layer, job: CellJob) -> "BaseGeometry | None":
    """One layer's planned deposit: the union of its passes' centre lines widened by their width
    (None: the layer has no pass with a point)."""
    # lazy: shapely loads only when this path runs (start-up time)
    from shapely.geometry import LineString, Point
    from shapely.ops import unary_union

    shapes = []
    for p in L.passes:
        pts = [(float(q[0]), float(q[1])) for q in p.points.tolist()]
        w = p.width_mm or job.job.bead.width_mm
        if len(pts) >= 2:
            shapes.append(LineString(pts).buffer(w / 2, cap_style="flat" if pts[0] != pts[-1] else "round"))
        elif pts:
            shapes.append(Point(pts[0]).buffer(w / 2))
    return unary_union(shapes) if shapes else None


def _core_candidates(core: "BaseGeometry", z: float) -> list[tuple[float, float, float, str]]:
    """Touch candidates on one layer's inset exposed top at height z: a grid inside it, and points
    spread along its edges."""
    # lazy: shapely loads only when this path runs (start-up time)
    from shapely.geometry import Point

    lo = np.array(core.bounds[:2])
    hi = np.array(core.bounds[2:])
    step = max(0.5, float(np.sqrt(core.area / 400.0)))
    xs = np.arange(lo[0], hi[0] + 1e-9, step)
    ys = np.arange(lo[1], hi[1] + 1e-9, step)
    grid = [(x, y) for x in xs for y in ys if core.contains(Point(x, y))]
    cand: list[tuple[float, float, float, str]] = [(x, y, z, "inside") for x, y in grid]
    for ring in ([core.exterior] if core.geom_type == "Polygon" else [g.exterior for g in core.geoms]):
        n = max(4, int(ring.length / max(step, 1.0)))
        cand += [(*ring.interpolate(k / n, normalized=True).coords[0], z, "edge") for k in range(n)]
    return cand


def _layer_candidates(foot: "list[BaseGeometry | None]", i: int, z: float, inset: float) -> list[tuple[float, float, float, str]]:
    """Touch candidates on layer i's exposed top (its footprint minus the layers above), `inset` in
    from its boundary; none when nothing of it is exposed that wide."""
    # lazy: shapely loads only when this path runs (start-up time)
    from shapely.ops import unary_union

    mine = foot[i]
    if mine is None or mine.is_empty:
        return []
    above = [f for f in foot[i + 1:] if f is not None]
    top = mine.difference(unary_union(above)) if above else mine
    core = top.buffer(-inset)
    if core.is_empty:
        return []
    return _core_candidates(core, z)


def _spread_pick(cand: list[tuple[float, float, float, str]], xy: np.ndarray,
                 n_inside: int, n_edge: int) -> list[int]:
    """Indices into cand: n_inside "inside" then n_edge "edge" touches by farthest-point sampling
    (the first inside one nearest their centre), each kind kept away from all picked before."""
    pick: list[int] = []
    for kind, n in (("inside", n_inside), ("edge", n_edge)):
        idx = [i for i, c in enumerate(cand) if c[3] == kind]
        if not idx:
            continue
        d = np.full(len(idx), np.inf)
        for j in pick:
            d = np.minimum(d, np.linalg.norm(xy[idx] - xy[j], axis=1))
        cur = idx[int(np.argmin(np.linalg.norm(xy[idx] - xy[idx].mean(axis=0), axis=1)))] if not pick else idx[int(np.argmax(d))]
        for _ in range(min(n, len(idx))):
            pick.append(cur)
            d = np.minimum(d, np.linalg.norm(xy[idx] - xy[cur], axis=1))
            cur = idx[int(np.argmax(d))]
    return list(dict.fromkeys(pick))


def verify_targets(job: CellJob, n_inside: int = 12, n_edge: int = 8) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Where to touch after the deposit, CAD frame: points on the deposit's exposed top, never on stock.

    The deposit is the union of the planned bead footprints (each pass's centre line widened by
    its width); the exposed top of a layer is its footprint minus the layers above. Touches go
    inside it, at least half a bead (and the probe's spread) in from its boundary, spread out by
    farthest-point sampling, and along its edges (half a bead in from the boundary, on the
    boundary's longest stretches). Returns (n, 2) xy, (n,) planned top z under each, and kinds.
    """
    layers = sorted(job.layers, key=lambda L: L.z_mm)
    foot = [_layer_footprint(L, job) for L in layers]
    w = job.job.bead.width_mm
    inset = 0.5 * w + 0.25
    cand: list[tuple[float, float, float, str]] = []
    for i, L in enumerate(layers):
        cand += _layer_candidates(foot, i, L.z_mm, inset)
    if not cand:
        raise InputError("repair verify: the planned deposit leaves no top a probe can touch (narrower than a bead)")
    xy = np.array([(c[0], c[1]) for c in cand])
    pick = _spread_pick(cand, xy, n_inside, n_edge)
    return xy[pick], np.array([cand[i][2] for i in pick]), [str(cand[i][3]) for i in pick]


def verify_split(n: int) -> tuple[int, int]:
    """How `n` verify touches divide: (inside the deposit's exposed top, along its edges)."""
    n_inside = n * 5 // 8
    return n_inside, n - n_inside


async def verify(link: CncLinkPort, cell: CellConfig, job: CellJob, transform: np.ndarray, grid: int = 4,
                 tolerance_mm: float = 0.1) -> VerifyResult:
    """Probe the deposit's exposed top (inside and along its edges, `verify_targets`); positions
    read back into the CAD frame and compared with the planned top under each touch."""

    if job.repair is None or job.repair.bounds_mm is None:
        raise InputError("job: not a repair job (no repair.bounds_mm); plan it with `cell repair plan`")
    rb = job.repair.bounds_mm
    xy, ztop, kinds = await asyncio.to_thread(verify_targets, job, *verify_split(grid * grid))   # off the device loop
    top = max(L.z_mm for L in job.layers)
    pts = await probe_cad_points(link, cell, np.asarray(xy, dtype=float), top, np.asarray(transform, dtype=float), name="verify")
    nominal = float(rb[1, 2])  # the repair volume's top: CAD + allowance
    return VerifyResult(pts, top, nominal, tolerance_mm, planned_z=ztop, kinds=tuple(kinds))


def _record(run_dir: Path, rec: dict[str, Any]) -> None:
    """The machining and its verify into the run's record: repair.json, and report.json's `repair`."""
    # stdlib, needed only on this path
    import json

    (run_dir / "repair.json").write_text(json.dumps(rec, indent=1) + "\n", encoding="utf-8")
    rp = run_dir / "report.json"
    if rp.is_file():
        data = json.loads(rp.read_text(encoding="utf-8"))
        data["repair"] = rec
        rp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")


def _rounded(v: float) -> float:
    return round(float(v), 4)


def _short_spots(pts: np.ndarray, margin: np.ndarray, need: float) -> str:
    bad = [f"({p[0]:.1f}, {p[1]:.1f}): {m:+.3f} mm" for p, m in zip(pts, margin) if not m >= need]
    return "; ".join(bad[:8]) + (f" and {len(bad) - 8} more" if len(bad) > 8 else "")


def machined_verify(pts: np.ndarray, err: np.ndarray, tolerance_mm: float) -> dict[str, Any]:
    """The verify against CAD (no allowance): per touch z − CAD top under it."""
    defects = []
    k = int(np.argmax(np.abs(err)))
    if abs(float(err[k])) > tolerance_mm:
        defects.append({"kind": "height", "at": np.round(pts[k], 3).tolist(), "error_mm": _rounded(err[k])})
    return {"points": len(err), "against": "CAD", "height_error_mean_mm": _rounded(err.mean()),
            "height_error_max_mm": _rounded(np.abs(err).max()), "flatness_mm": _rounded(err.max() - err.min()),
            "below_cad_max_mm": _rounded(max(0.0, -float(err.min()))), "tolerance_mm": tolerance_mm,
            "defects": defects, "at": np.round(pts, 3).tolist(), "error_mm": np.round(err, 4).tolist()}


REFINE_MM = (1.0, 0.5)   # the stock probe's spacing around low touches, then around the short among those
REFINE_BAND_MM = 0.1     # a touch this close to short is refined around at 1 mm as a short one is
REFINE_MAX = 160         # touches a refinement adds at most (nearest the low touches first)
FLOOD_ROUNDS = 12        # rings of cells the flood traces out from the low touches at most
FLOOD_BAND_MM = 0.3      # the flood goes on through cells standing under min_stock + this


async def _touch_refined(link: CncLinkPort, cell: CellConfig, cad_tri: np.ndarray, stock_tri: np.ndarray, rb: np.ndarray,
                         spots: np.ndarray, top: float, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Touch the spots, then around every touch standing less than `min_stock_mm` + `REFINE_BAND_MM`
    over CAD at 1 mm, then around the short ones of those at 0.5 mm (`refine_spots`, at most
    `REFINE_MAX` each); all touches (CAD frame) and their heights over CAD."""
    m = cell.machining
    scan = scan_settings(cell.probe)
    pts = await probe_cad_points(link, cell, spots, top, transform, "stock", scan)
    margin = await asyncio.to_thread(stock_margin, cad_tri, pts)
    fresh = np.ones(len(pts), dtype=bool)
    for k, spacing in enumerate(REFINE_MM):
        low = fresh & ~(margin >= m.min_stock_mm + (REFINE_BAND_MM if k == 0 else 0.0))
        more = (await asyncio.to_thread(refine_spots, cad_tri, stock_tri, rb, pts[:, :2], low, spacing))[:REFINE_MAX]
        if not len(more):
            break
        got = await probe_cad_points(link, cell, more, top, transform, "stock", scan)
        pts, margin = np.vstack([pts, got]), np.concatenate([margin, await asyncio.to_thread(stock_margin, cad_tri, got)])
        fresh = np.r_[np.zeros(len(fresh), dtype=bool), np.ones(len(got), dtype=bool)]
    # trace every stretch standing under the need + the band cell by cell to its end, so a round of
    # depositing again gets every short spot at once; not while the deposit is short all over (its
    # spots' median under the need + the band): whole layers follow (controller/job/redeposit.py)
    short_all_over = float(np.median(margin[:len(spots)])) < m.min_stock_mm + REFINE_BAND_MM
    for _ in range(0 if short_all_over else FLOOD_ROUNDS):
        more = await asyncio.to_thread(flood_spots, cad_tri, stock_tri, rb, pts[:, :2],
                                       ~(margin >= m.min_stock_mm + FLOOD_BAND_MM))
        if not len(more):
            break
        got = await probe_cad_points(link, cell, more, top, transform, "stock", scan)
        pts, margin = np.vstack([pts, got]), np.concatenate([margin, await asyncio.to_thread(stock_margin, cad_tri, got)])
    return pts, margin


def _cad_high(cad_tri: np.ndarray, job: CellJob, step_mm: float = 0.5) -> float:
    """The CAD's highest top over the repair region's xy bounds (a 0.5 mm grid and its corners)."""
    assert job.repair is not None and job.repair.bounds_mm is not None
    (x0, y0, _z0), (x1, y1, _z1) = np.asarray(job.repair.bounds_mm, dtype=float)
    gx, gy = np.meshgrid(np.r_[np.arange(x0, x1, step_mm), x1], np.r_[np.arange(y0, y1, step_mm), y1])
    z = cad_top(cad_tri, np.column_stack([gx.ravel(), gy.ravel()]))
    return float(np.max(z[np.isfinite(z)])) if np.isfinite(z).any() else -np.inf


async def probe_stock(link: CncLinkPort, cell: CellConfig, job: CellJob, cad_tri: np.ndarray, stock_tri: np.ndarray,
                      spots: np.ndarray, transform: np.ndarray, say: Callable[[str], None],
                      deposit_again: Callable[[CellJob], Awaitable[float]] | None) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
    """The stock probe (refined around low touches, `_touch_refined`), and where it finds the
    deposit short, deposit again there and probe again, at most `machining.redeposit_rounds` times
    (docs/machining.md "Deposit again"), every spot of the round before touched again (the refined
    ones too); returns the touches (CAD frame), their heights over CAD and the rounds deposited.
    Still short: CellError naming the spots."""
    m = cell.machining
    # the highest the surface may stand under the spots: the planned top, or the CAD within the region
    top = max(float(max(L.z_mm for L in job.layers)), await asyncio.to_thread(_cad_high, cad_tri, job)) + 1.0
    rounds: list[dict[str, Any]] = []
    target = m.min_stock_mm + REFINE_BAND_MM   # not the allowance: a bead laid again overshoots it anyway
    assert job.repair is not None and job.repair.bounds_mm is not None
    rb = np.asarray(job.repair.bounds_mm, dtype=float)
    n_base = len(spots)   # the ring and grid spots lead every round's touches (the refined ones follow)
    while True:
        say("stock")
        pts, margin = await _touch_refined(link, cell, cad_tri, stock_tri, rb, spots, top, transform)
        short = ~(margin >= m.min_stock_mm)
        if not short.any():
            return pts, margin, rounds
        if deposit_again is None or len(rounds) >= m.redeposit_rounds:
            again = f" after {len(rounds)} round(s) of depositing again" if rounds else ""
            raise CellError(f"repair: the deposit stands less than {m.min_stock_mm} mm above CAD{again} at "
                            f"{_short_spots(pts, margin, m.min_stock_mm)}; deposit again there (or plan a larger "
                            "allowance)")
        # the deposit's typical height: the median of the ring and grid touches (the refined ones sit where it is low)
        base = slice(0, n_base)
        typical = (float(np.median(margin[base])), float(np.median(pts[base, 2])))
        extra = await asyncio.to_thread(redeposit_job, job, pts[short], margin[short], target, round_no=len(rounds) + 1,
                                        typical=typical)
        say("build")
        passes = await deposit_again(extra)
        rounds.append({"short_spots": int(short.sum()), "min_mm": _rounded(np.nanmin(margin)),
                       "typical_mm": _rounded(typical[0]), "layers": len(extra.layers), "passes": int(passes)})
        spots = pts[:, :2]   # every spot touched, the refined ones too: probed again after the deposit
        top = max(top, float(max(L.z_mm for L in extra.layers)) + 1.0)


async def finish_repair(link: CncLinkPort, cell: CellConfig, job: CellJob, cad: "trimesh.Trimesh", stock: "trimesh.Trimesh", transform: np.ndarray,
                        say: Callable[[str], None],
                        deposit_again: Callable[[CellJob], Awaitable[float]] | None = None) -> dict[str, Any]:
    """Probe the deposit (depositing again where short, `deposit_again` builds a job on the cell),
    rough and finish it to CAD, verify against CAD (docs/contract.md §4, docs/machining.md)."""
    m = cell.machining
    name, cutter = cell.tools.cutter(m.cutter)
    cad_tri, stock_tri = np.asarray(cad.triangles, dtype=float), np.asarray(stock.triangles, dtype=float)
    assert job.repair is not None and job.repair.bounds_mm is not None
    rb = np.asarray(job.repair.bounds_mm, dtype=float)
    # every computation off the loop that cycles the devices (a pocket's plan is seconds of CPU on a
    # loaded host: the CNC link's status poll would go silent meanwhile, docs/testing.md)
    spots, kinds = await asyncio.to_thread(stock_spots, cad_tri, stock_tri, rb)     # dense where a deposit falls short
    vspots = await asyncio.to_thread(repaired_spots, cad_tri, stock_tri, rb, m.probe_points)
    pts, margin, rounds = await probe_stock(link, cell, job, cad_tri, stock_tri, spots, transform, say, deposit_again)
    top = float(np.nanmax(pts[:, 2])) + 1.0
    stock_rec = {"min_mm": _rounded(np.nanmin(margin)), "max_mm": _rounded(np.nanmax(margin)), "points": len(pts),
                 "kinds": {**{k: kinds.count(k) for k in ("corner", "ring", "inside")}, "refined": len(pts) - len(spots)},
                 "redeposits": rounds,
                 "min_stock_mm": m.min_stock_mm, "at": np.round(pts, 3).tolist()}
    lo, hi = np.asarray(cad.bounds, dtype=float)
    region = (float(max(rb[0, 0] - m.margin_mm, lo[0])), float(max(rb[0, 1] - m.margin_mm, lo[1])),
              float(min(rb[1, 0] + m.margin_mm, hi[0])), float(min(rb[1, 1] + m.margin_mm, hi[1])))
    cut = Cut(name, ToolShape(cutter.type, cutter.radius_mm), cutter.max_depth_of_cut_mm, cutter.max_stepover_mm,
              cutter.feed_mm_min, cell.limits.travel_speed_mm_min)

    def machining_plan() -> tuple[FinishPlan, float, list[str]]:
        surf = stock_surface(cad_tri, pts, region, grow_mm=m.margin_mm, ripple_mm=m.ripple_mm)
        plan = plan_finish(cad_tri, surf, region, cut, finish_stock_mm=m.finish_stock_mm, scallop_mm=m.scallop_mm)
        removal = stock_above_cad(cad_tri, stock_surface(cad_tri, pts, region, grow_mm=m.margin_mm, ripple_mm=0.0))
        return plan, removal, program_lines(plan, transform, cutter)

    plan, removal, lines = await asyncio.to_thread(machining_plan)
    say("machine")
    clear_z = float((np.asarray(transform) @ np.array([0.0, 0.0, plan.safe_z_mm, 1.0]))[2]) + 10.0
    await change_tool(link, cell.tools, cutter.number, clear_z)
    wall_s = await run_program(link, lines)
    await change_tool(link, cell.tools, cell.tools.deposition.number, clear_z)
    say("verify")
    vpts = await probe_cad_points(link, cell, vspots, top, transform, "verify")
    verify = machined_verify(vpts, await asyncio.to_thread(stock_margin, cad_tri, vpts), m.verify_tolerance_mm)
    machining = {"tool": name, "removal_mm3": _rounded(removal), "wall_s": round(wall_s, 2),
                 "est_time_s": round(plan.est_time_s, 1), "passes": len(plan.passes), "levels": plan.levels,
                 "scallop_mm": _rounded(plan.scallop_mm), "stepover_mm": _rounded(plan.stepover_mm),
                 "region_mm": [round(v, 3) for v in region],
                 "removal_mean_mm": _rounded(removal / max((region[2] - region[0]) * (region[3] - region[1]), 1e-9))}
    return {"stock": stock_rec, "machining": machining, "verify": verify}


def repair_cell(cell: CellConfig) -> CellConfig:
    """The cell a repair runs on: its CNC (the platform set to `cnc`)."""
    if cell.cell.platform == "cnc":
        return cell
    return cell.model_copy(update={"cell": cell.cell.model_copy(update={"platform": "cnc"})})


def _deposit_again(ctl: CellController, res: AlignResult, apply_alignment: bool) -> Callable[[CellJob], Awaitable[float]]:
    """Build a job (CAD frame) on the controller, on the repair's alignment; returns its passes done."""
    async def build(extra: CellJob) -> float:
        # moved, checked and journaled off the loop that cycles the devices, as the repair's own build
        built = await asyncio.to_thread(apply_to_job, extra, res.transform, alignment_record(res)) if apply_alignment else extra
        await asyncio.to_thread(ctl.open_job, built)
        got = await ctl.start()
        if got.state != "complete":
            raise Fault(f"repair: depositing again stopped in state {got.state}; see the journal in {ctl.run_dir}",
                        state=got.state)
        return float(got.passes_done)

    return build


async def repair_run(ctl: CellController, job: CellJob, *, job_path: Path | None = None, apply_alignment: bool = True,
                     tolerance_mm: float = 0.1, phase: Callable[[str], None] | None = None,
                     finish: bool = True, time_scale_of: Callable[[str], float] | None = None) -> dict[str, Any]:
    """The whole chain on the CNC cell `ctl` was opened on, not yet connected (controller/harness/cell.py
    `open_cell(repair_cell(cfg), connect=False)`: hardware, `cell sim up` or the in-process
    simulators); returns the report. `phase(name)` is told "align", "build" and "verify" as each
    begins, the machine idle (the harness sets its clock). The cell is closed at the end."""
    say = phase or (lambda _name: None)
    cell = ctl.cfg
    if cell.cell.platform != "cnc":
        raise InputError(f"a repair runs on the CNC: cell.yaml's platform is {cell.cell.platform} "
                         "(open the cell with controller.repair.repair_cell(cfg))")
    if job.alignment is not None:
        raise InputError("the repair job already carries an alignment; give the job `cell repair plan` wrote")
    cad = load_cad(job, job_path)
    plan = probe_plan(cad, job)
    # every refusal that needs no device before the first motion (homing and probing included):
    # a time scale the CNC link cannot feed in any topology (the command that started the simulators
    # lowered the scale to what the host feeds where they run: controller/motion/cnc5.py)
    refuse_unfed(job, Trunnion.from_config(cell.kinematics), float(cell.cell.time_scale), cell.devices.cnc.baud,
                 beside=True)
    stops.attach(ctl)  # SIGINT / SIGTERM / SIGHUP: the fault path (when the CLI installed them)
    try:
        await ctl.connect()
        say("align")
        res = await ctl.run_alignment(plan)
        # the job moved, checked and journaled off the loop that cycles the devices (docs/testing.md)
        built = await asyncio.to_thread(apply_to_job, job, res.transform, alignment_record(res)) if apply_alignment else job
        await asyncio.to_thread(ctl.open_job, built)
        say("build")
        result = await ctl.start()
        if result.state != "complete":
            raise Fault(f"repair: the build stopped in state {result.state}; see the journal in {ctl.run_dir}",
                        state=result.state)
        if ctl.devices is None:
            raise CellError("repair: the cell's devices closed before the verify probe")
        run_dir, last_report = Path(str(ctl.run_dir)), ctl.last_report   # the repair's record: its own build's
        if finish:
            stock = await asyncio.to_thread(load_cad, job, job_path, "stock")
            fin = await finish_repair(ctl.devices.cnc_link(), cell, job, cad, stock,
                                      res.transform, say, _deposit_again(ctl, res, apply_alignment))
            scale = time_scale_of("machine") if time_scale_of is not None else float(cell.cell.time_scale)
            fin["machining"]["time_s"] = round(fin["machining"].pop("wall_s") * scale, 1)
            v = fin["verify"]
        else:
            say("verify")
            v = (await verify(ctl.devices.cnc_link(), cell, job, res.transform, tolerance_mm=tolerance_mm)).as_dict()
    finally:
        stops.detach()
        await ctl.close()
    report = str(last_report) if last_report else None
    if finish:
        _record(run_dir, {k: fin[k] for k in ("stock", "machining", "verify")})
        if cell.records.url:   # the store had the record at the build's end: send it again with the machining
            # lazy: the records room loads only for a cell with a store
            from controller.records.queue import resend

            await asyncio.to_thread(resend, run_dir, cell.records.url, cell=cell.cell.name,
                                    timeout_s=cell.records.connect_timeout_s)
    return {"state": result.state, "level_a_deg": round(res.level_a_deg, 5), "level_b_deg": round(res.level_b_deg, 5),
            "face_angle_deg": round(res.face_angle_deg, 5),
            "transform": np.round(np.asarray(res.transform, dtype=float), 9).tolist(),
            "passes_done": result.passes_done, "verify": v, "report": report,
            **({k: fin[k] for k in ("stock", "machining")} if finish else {}),
            "defects": v["defects"], "run_dir": str(run_dir),
            # the shapes of issue 17, kept for scripts that read them
            "alignment": {"level_a_deg": round(res.level_a_deg, 5), "level_b_deg": round(res.level_b_deg, 5),
                          "face_angle_deg": round(res.face_angle_deg, 5)},
            "build": {"state": result.state, "passes_done": result.passes_done, "run_dir": str(run_dir)}}

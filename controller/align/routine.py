"""`cell align run`: home/unlock, probe the top, level with A/B, probe the side face, transform.

Padathu 2005's procedure on the cell's CNC (docs/contract.md §4):
1. home (or unlock) as needed; probe a grid on the top face;
2. fit the top plane in the table frame and move A/B to the unique leveling angles;
3. probe the side face (a row of touches along it) and one touch on a third face;
4. the face angle between the fitted side face and the CAD face (eq. 1), and the CAD model
   rotated to match — the part is not moved again;
5. the CAD → machine transform (3-2-1 on top, side, third face), checked by ICP on the mesh.

The nominal part ("CAD") is the simulator config's workpiece description (a block of size_mm
with its top face at z = 0, centred in X/Y, or a mesh file) or `--cad FILE`; it sits nominally
at the table origin. Everything returned is a frozen AlignResult.
"""
from __future__ import annotations

import asyncio
import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from numpy.typing import NDArray

from controller.align.bestfit import icp
from controller.align.fit import Datum, LineFit, PlaneFit, cad_transform_321, fit_line, fit_plane, grid_points
from controller.motion.kinematics import Trunnion, apply_transform, homogeneous, rotation_matrix, unit
from controller.align.leveling import FaceAngle, Leveling, face_angle, leveling_angles
from controller.align import watched
from controller.align.probe_cycle import ProbedPoint, ProbeLog, ProbeTarget, probe_points
from drivers.registry import open_cnc
from wire.grbl_protocol import fmt
from controller.ports import CncLinkPort, ProbePort
from core.config import CellConfig, ProbeSettings, Workpiece
from core.errors import InputError

if TYPE_CHECKING:  # trimesh loads on first use (start-up time)
    import trimesh

F = NDArray[np.float64]
Z = np.array([0.0, 0.0, 1.0])


# --- the probe plan (pure) -------------------------------------------------------------------------


@dataclass(frozen=True)
class ProbePlan:
    """Where to touch, in CAD coordinates (top face z = top_z, side face x = side_x, third y = tertiary_y)."""

    top_xy: F                    # (k, 2) grid on the top face
    top_z: float
    side_x: float                # the +X face (its CAD normal is +X)
    side_y: F                    # touches along it
    side_z: float                # depth of the side and third-face touches
    tertiary_xy: tuple[float, float]  # the touch on the -Y face: (x, y of the face)
    bounds: F                    # (2, 3) CAD bounding box
    mesh: trimesh.Trimesh | None = None   # the CAD, for the ICP check

    @property
    def datums(self) -> tuple[Datum, Datum, Datum]:
        return (Datum((0.0, 0.0, 1.0), (0.0, 0.0, self.top_z)), Datum((1.0, 0.0, 0.0), (self.side_x, 0.0, self.side_z)),
                Datum((0.0, -1.0, 0.0), (self.tertiary_xy[0], self.tertiary_xy[1], self.side_z)))


def plan_for_mesh(mesh: trimesh.Trimesh, *, grid: tuple[int, int] = (3, 3), top_span_mm: float | None = None,
                  side_touches: int = 5, side_span_mm: float | None = None, margin_mm: float = 10.0,
                  depth_mm: float = 5.0, top_xy: F | None = None, side_y: F | None = None,
                  tertiary_x: float | None = None) -> ProbePlan:
    """A plan on a block-like CAD mesh: top grid within the top face, +X face row, one touch on -Y.

    `top_xy`, `side_y`, `tertiary_x` (a repair: spots off its region, controller/align/intact.py)
    replace the grid, the row and the third touch's x."""
    lo, hi = np.asarray(mesh.bounds, dtype=float)
    size = hi - lo
    ctr = (lo + hi) / 2
    span_x = top_span_mm if top_span_mm is not None else size[0] - 2 * margin_mm
    span_y = top_span_mm if top_span_mm is not None else size[1] - 2 * margin_mm
    if top_xy is None and (span_x <= 0 or span_y <= 0 or span_x >= size[0] or span_y >= size[1]):
        raise InputError(f"probe plan: a top grid over {span_x:.1f} × {span_y:.1f} mm does not fit inside the "
                         f"{size[0]:.1f} × {size[1]:.1f} mm top face with room to spare; use a larger part or a smaller grid")
    side_span = side_span_mm if side_span_mm is not None else size[1] - 2 * margin_mm
    depth = min(depth_mm, size[2] / 2)
    ys = np.linspace(ctr[1] - side_span / 2, ctr[1] + side_span / 2, side_touches) if side_touches > 1 else np.array([ctr[1]])
    if side_y is not None:
        ys = np.asarray(side_y, dtype=float)
    top = np.asarray(top_xy, dtype=float) if top_xy is not None else grid_points(ctr, (span_x, span_y), grid)
    tx = float(ctr[0]) if tertiary_x is None else float(tertiary_x)
    return ProbePlan(top_xy=top, top_z=float(hi[2]), side_x=float(hi[0]),
                     side_y=ys, side_z=float(hi[2] - depth), tertiary_xy=(tx, float(lo[1])),
                     bounds=np.array([lo, hi]), mesh=mesh)


def cad_mesh(workpiece: Workpiece | None = None, cad_path: str | Path | None = None,
             base_dir: Path | None = None) -> trimesh.Trimesh:
    """The nominal part: `--cad FILE`, else the sim config's workpiece (mesh, or a block of size_mm, top at z = 0)."""
    # lazy: trimesh loads only when this path runs (start-up time)
    import trimesh

    path = cad_path or (workpiece.mesh if workpiece is not None else None)
    if path:
        p = Path(path)
        if not p.is_absolute() and base_dir is not None and (base_dir / p).exists():
            p = base_dir / p
        try:
            mesh: trimesh.Trimesh = trimesh.load_mesh(str(p), force="mesh")   # force="mesh": one Trimesh
        except Exception as exc:  # trimesh raises many kinds
            raise InputError(f"{p}: cannot load the CAD mesh ({exc}); give an STL/OBJ/3MF file in mm") from None
        return mesh
    sx, sy, sz = workpiece.size_mm if workpiece is not None else (100.0, 100.0, 20.0)
    box: trimesh.Trimesh = trimesh.creation.box(extents=(sx, sy, sz))
    box.apply_translation((0.0, 0.0, -sz / 2.0))
    return box


# --- result ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AlignResult:
    level_a_deg: float
    level_b_deg: float           # B (AB table) or C (AC table)
    face_angle_deg: float        # signed, about +Z of the leveled table: CAD +X face → fitted side face
    face_angle_eq1_deg: float    # Padathu eq. 1, unsigned
    transform: F                 # 4×4 CAD → machine at the leveled table angles
    transform_table: F           # 4×4 CAD → table frame (A = B = 0)
    top: PlaneFit                # in the leveled machine frame
    top_table: PlaneFit          # as probed, in the table frame
    side: LineFit                # the row of side touches, leveled machine frame
    side_normal: F
    tertiary: F
    leveling: Leveling
    face: FaceAngle
    residual_tilt_deg: float     # top re-probed after leveling: its normal vs +Z (should be ~0)
    icp_rms_mm: float            # RMS distance of every touch to the CAD surface after ICP
    icp_shift_mm: float          # how far ICP moved the CAD's corners from the 3-2-1 transform
    points: dict[str, F] = field(default_factory=dict)  # name → (k, 3) in the leveled machine frame
    probed: tuple[ProbedPoint, ...] = ()
    log: tuple[str, ...] = ()
    no_level: bool = False       # `--no-level`: no A/B commanded; the measured tilt is in the transform

    def planes(self) -> list[dict[str, Any]]:
        t, s = self.top, self.side
        return [
            {"name": "top", "normal": t.normal.tolist(), "point": t.point.tolist(), "rms_mm": t.rms_mm,
             "max_residual_mm": t.max_residual_mm, "outliers": list(t.outliers), "n_points": t.n_points,
             "chi2_ok": t.chi2_ok, "normal_as_probed": self.top_table.normal.tolist()},
            {"name": "side", "normal": self.side_normal.tolist(), "point": s.point.tolist(), "rms_mm": s.rms_mm,
             "max_residual_mm": s.max_residual_mm, "outliers": [], "n_points": int(len(self.points.get("side", [])))},
            {"name": "tertiary", "normal": None, "point": self.tertiary.tolist(), "rms_mm": 0.0,
             "max_residual_mm": 0.0, "outliers": [], "n_points": 1},
        ]

    def to_json(self) -> dict[str, Any]:
        return {
            "planes": self.planes(), "level_a_deg": self.level_a_deg, "level_b_deg": self.level_b_deg,
            "face_angle_deg": self.face_angle_deg, "face_angle_eq1_deg": self.face_angle_eq1_deg,
            "transform": self.transform.tolist(), "transform_table": self.transform_table.tolist(),
            "residual_tilt_deg": self.residual_tilt_deg, "icp_rms_mm": self.icp_rms_mm,
            "icp_shift_mm": self.icp_shift_mm, "no_level": self.no_level, "tilt_deg": self.leveling.tilt_deg,
            "cad_rotation_deg": self.face.signed_deg,
            "points": {k: v.tolist() for k, v in self.points.items()},
        }


# --- the pure part of the routine -------------------------------------------------------------------


def _min_rotation(a: F, b: F) -> F:
    """Smallest rotation taking unit a onto unit b."""
    a, b = unit(a), unit(b)
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    if s < 1e-15:
        return np.eye(3)
    return rotation_matrix(axis / s, float(np.degrees(np.arctan2(s, a @ b))))


def top_estimate(top_table: PlaneFit, plan: ProbePlan) -> F:
    """CAD → table guess from the top plane alone: tilted to the fitted normal, on the plane."""
    r = _min_rotation(Z, top_table.normal)
    # The CAD top centre lands on the fitted plane right under its nominal x, y.
    c = np.array([0.0, 0.0, plan.top_z])
    n, d = top_table.normal, top_table.offset
    rc = r @ c
    # Solve n·(rc + t) = d with t vertical: t = (0, 0, (d − n·rc)/n_z).
    t = np.array([0.0, 0.0, (d - n @ rc) / n[2]])
    return homogeneous(r, t)


def solve_alignment(top_pts_table: F, side_pts: F, tertiary_pt: F, side_approach: F, plan: ProbePlan,
                    table: Trunnion, level: Leveling, noise_mm: float | None, verify_pts: F | None = None,
                    probed: tuple[ProbedPoint, ...] = (), log: tuple[str, ...] = ()) -> AlignResult:
    """Everything after the touches: fits, face angle, 3-2-1 transform, ICP check (pure).

    `side_pts`, `tertiary_pt` and `verify_pts` (top re-probed after leveling) are in the
    machine frame at the leveled table angles.
    """
    top_table = fit_plane(top_pts_table, toward=Z, noise_mm=noise_mm)
    m_lev = table.matrix(level.a_deg, level.second_deg)
    top_l_pts = apply_transform(m_lev, top_pts_table)
    top = fit_plane(top_l_pts, toward=Z, noise_mm=noise_mm)
    line = fit_line(side_pts)
    n_side = np.cross(line.direction, top.normal)
    n_side = unit(n_side)
    if n_side @ (-side_approach) < 0:
        n_side = -n_side
    cad_top, cad_side, cad_ter = plan.datums
    fa = face_angle(n_side, cad_side.normal, about=Z)
    m = cad_transform_321(top.normal, top.point, n_side, line.point, tertiary_pt,
                          cad_top=cad_top, cad_side=cad_side, cad_tertiary=cad_ter)
    all_pts = np.vstack([top_l_pts[list(np.flatnonzero(top.inliers))], side_pts, tertiary_pt[None, :]])
    icp_rms = icp_shift = float("nan")
    if plan.mesh is not None:
        # Full rigid best fit of every touch against the CAD mesh, started from the 3-2-1 result:
        # its RMS says how well the CAD explains the touches, its shift how far 3-2-1 was off.
        fit = icp(all_pts, plan.mesh, initial=m)
        icp_rms = fit.rms_mm
        lo, hi = plan.bounds
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        icp_shift = float(np.linalg.norm(apply_transform(fit.matrix, corners) - apply_transform(m, corners), axis=1).max())
    if verify_pts is not None and len(verify_pts) >= 3:
        vn = fit_plane(verify_pts, toward=Z, reject=False).normal
        resid = float(np.degrees(np.arccos(np.clip(vn @ Z, -1, 1))))
    else:
        resid = float("nan")
    return AlignResult(
        level_a_deg=level.a_deg, level_b_deg=level.second_deg, face_angle_deg=fa.signed_deg,
        face_angle_eq1_deg=fa.angle_deg, transform=m, transform_table=np.linalg.inv(m_lev) @ m,
        top=top, top_table=top_table, side=line, side_normal=n_side, tertiary=np.asarray(tertiary_pt, dtype=float),
        leveling=level, face=fa, residual_tilt_deg=resid, icp_rms_mm=icp_rms, icp_shift_mm=icp_shift,
        points={"top": top_l_pts, "side": np.asarray(side_pts), "tertiary": np.asarray(tertiary_pt)[None, :]},
        probed=probed, log=log)


# --- the routine over the wire ------------------------------------------------------------------------


async def _ensure_ready(link: ProbePort, log: ProbeLog) -> None:
    st = await link.status()
    if not link.homed:
        log.add("homing ($H)")
        await watched.home(link)   # the homing cycle's bound from the machine's settings
    elif st.state.startswith("Alarm"):
        log.add("unlocking ($X)")
        await link.unlock()
    await link.command("G90 G21")


def _spread_triangle(xy: F) -> list[int]:
    """Three of the grid points spanning the largest triangle (well conditioned for a plane)."""
    if len(xy) <= 3:
        return list(range(len(xy)))
    i = 0
    j = int(np.argmax(np.linalg.norm(xy - xy[i], axis=1)))
    d = xy[j] - xy[i]
    k = int(np.argmax(np.abs(d[0] * (xy[:, 1] - xy[i, 1]) - d[1] * (xy[:, 0] - xy[i, 0]))))
    return sorted({i, j, k})


def _safe_z(plan: ProbePlan, m: F, clearance: float) -> float:
    lo, hi = plan.bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(apply_transform(m, corners)[:, 2].max() + clearance)


async def align(link: CncLinkPort, cell: CellConfig, plan: ProbePlan, *, settings: ProbeSettings | None = None,
                verify: bool = True,
                on_point: Callable[[ProbedPoint], None] | None = None, no_level: bool = False) -> AlignResult:
    """Run the whole routine on a connected CncLink; returns the frozen result.

    `no_level` (a 3-axis CNC, `cell align run --no-level`): the tilt is measured and carried in
    the transform; no A/B move is commanded. Otherwise the firmware's axes are checked before
    homing: a 3-axis firmware is refused naming what it lacks (exit 2)."""
    s = settings or cell.probe
    table = Trunnion.from_config(cell.kinematics)
    if not no_level:
        link.require_axes("XYZ" + table.table, "alignment (it levels the table with the rotary axes; "
                "`cell align run --no-level` measures the tilt without moving them)")
    log = ProbeLog()
    await _ensure_ready(link, log)
    st = await link.status()
    a0, b0 = float(st.mpos[3]), float(st.mpos[4])
    m0 = table.matrix(a0, b0)
    clear = float(s.clearance_mm)
    safe0 = _safe_z(plan, m0, clear)
    down = m0[:3, :3] @ -Z
    tops = [ProbeTarget(f"top[{i}]", tuple(apply_transform(m0, [x, y, plan.top_z + clear])), tuple(down), safe0)
            for i, (x, y) in enumerate(plan.top_xy)]
    got_top = await probe_points(link, tops, s, log, on_point)
    top_table = np.array([apply_transform(np.linalg.inv(table.matrix(*p.table_deg)), p.position) for p in got_top])
    # Each point is the mean of `samples` touches: its noise is σ/√samples.
    noise = float(s.noise_mm) / np.sqrt(max(int(s.samples), 1)) if float(s.noise_mm) > 0 else None
    top_fit = fit_plane(top_table, toward=Z, noise_mm=noise)
    level = leveling_angles(top_fit.normal, table)
    log.add(f"top: tilt {level.tilt_deg:.4f}°, leveling A {level.a_deg:.5f}°, B {level.second_deg:.5f}°")
    if no_level:  # the table stays where it is: the transform carries the measured tilt
        level = dataclasses.replace(level, a_deg=a0, second_deg=b0)
        log.add(f"--no-level: table kept at A {a0:.5f}°, B {b0:.5f}°; the tilt is in the transform")

    # Level the table: retract clear of the part in both poses, then turn A and B.
    m_lev = table.matrix(level.a_deg, level.second_deg)
    safe = max(safe0, _safe_z(plan, m_lev, clear))
    await link.command(f"G90 G0 Z{fmt(safe)}")
    if not no_level:
        await link.command(f"G0 A{fmt(level.a_deg)} B{fmt(level.second_deg)}")
    await link.wait_idle()

    est = m_lev @ top_estimate(top_fit, plan)
    r_est = est[:3, :3]
    sides = [ProbeTarget(f"side[{i}]", tuple(apply_transform(est, [plan.side_x + clear, y, plan.side_z])),
                         tuple(r_est @ np.array([-1.0, 0.0, 0.0])), safe) for i, y in enumerate(plan.side_y)]
    tx, ty = plan.tertiary_xy
    ters = [ProbeTarget("third[0]", tuple(apply_transform(est, [tx, ty - clear, plan.side_z])),
                        tuple(r_est @ np.array([0.0, 1.0, 0.0])), safe)]
    # Re-probe three top points after leveling: the residual tilt proves the table moved right.
    pick = _spread_triangle(plan.top_xy)
    checks = [ProbeTarget(f"level-check[{i}]", tuple(apply_transform(est, [*plan.top_xy[i], plan.top_z + clear])),
                          tuple(r_est @ -Z), safe) for i in pick]
    got_check = await probe_points(link, checks, s, log, on_point) if verify else []
    got_side = await probe_points(link, sides, s, log, on_point)
    got_ter = await probe_points(link, ters, s, log, on_point)
    await link.command(f"G90 G0 Z{fmt(safe)}")
    await link.wait_idle()

    def leveled(p: ProbedPoint) -> F:
        return apply_transform(m_lev @ np.linalg.inv(table.matrix(*p.table_deg)), p.position)

    side_pts = np.array([leveled(p) for p in got_side])
    ter_pt = leveled(got_ter[0])
    verify_pts = np.array([leveled(p) for p in got_check]) if got_check else None
    # the fits and the ICP check off the loop that cycles the devices (docs/testing.md)
    res = await asyncio.to_thread(lambda: solve_alignment(
        top_table, side_pts, ter_pt, np.asarray(sides[0].direction), plan, table, level, noise,
        verify_pts=verify_pts, probed=tuple(got_top + got_check + got_side + got_ter), log=tuple(log.lines)))
    return dataclasses.replace(res, no_level=True) if no_level else res


# --- CLI glue ------------------------------------------------------------------------------------------


async def run_on_url(url: str, cell: CellConfig, plan: ProbePlan, *, settings: ProbeSettings | None = None,
                     on_point: Callable[[ProbedPoint], None] | None = None, no_level: bool = False) -> AlignResult:
    """Open the CNC link at `url`, align, close the link (also when cancelled)."""
    link = open_cnc(cell.devices.cnc, time_scale=cell.cell.time_scale, url=url)
    await link.connect()
    try:
        return await align(link, cell, plan, settings=settings, on_point=on_point, no_level=no_level)
    except BaseException as exc:
        # any error or stop (a signal cancels the task): never leave the CNC in Hold with lines
        # queued (docs/contract.md §6): feed hold, M5 or a soft reset, verified
        if link.connected:
            await link.safe_stop(f"alignment stopped: {exc or type(exc).__name__}")
        raise
    finally:
        await link.close()


def alignment_record(res: "AlignResult") -> dict[str, Any]:
    """The job's `alignment` (docs/contract.md §3): transform, table angles, when it was probed."""
    no_level = res.no_level
    return {"transform": res.transform.tolist(), "level_a_deg": res.level_a_deg, "level_b_deg": res.level_b_deg,
            **({"no_level": True, "tilt_deg": res.leveling.tilt_deg} if no_level else {}),
            "table_deg": {"a": res.level_a_deg, "b": res.level_b_deg}, "face_angle_deg": res.face_angle_deg,
            "probed_at": time.time()}


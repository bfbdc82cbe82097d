"""`cell align plane|transform|run`: probe-and-align on the 5-axis CNC (docs/contract.md §4, §7)."""
from __future__ import annotations

import argparse
import asyncio
import csv
import re
import sys
from pathlib import Path

import numpy as np

from controller.api import align_at, aligned_job
from controller.api.geometry import (alignment_record, fit_and_level, probe_plan_on, read_rotations,
                                     rotate_points, write_align_report)
from controller.api.jobs import read_job
from controller.api.types import ProbedPoint
from controller.cli import guard
from controller.cli.parsing import NumbersParser, Subcommands
from controller.harness import run_with_sim
from core.config import load_cell, load_sim
from core.errors import InputError

def register(sub: Subcommands) -> None:
    p = sub.add_parser("align", help="probe, fit, level and align the workpiece on the CNC")
    # the align parsers read words such as "-1,-1,-5" as values (`--pivot -1,-1,-5`, a point `-1,2,3`)
    s = p.add_subparsers(dest="align_command", metavar="SUBCOMMAND", parser_class=NumbersParser)
    s.required = True

    pl = s.add_parser("plane", help="fit a plane to x,y,z points of a CSV file")
    pl.add_argument("csv", metavar="CSV", help="points, columns x, y, z (mm; header optional)")
    pl.add_argument("--noise", type=float, default=None, metavar="MM",
                    help="probe noise 1σ for the χ² check and outlier test (default cell.yaml probe.noise_mm)")
    pl.add_argument("--no-reject", action="store_true", help="keep every point (no outlier rejection)")
    pl.add_argument("--cell-config", default=None, metavar="FILE", help="cell config (default config/cell.yaml)")
    pl.add_argument("--json", action="store_true", help="print one JSON object")
    pl.set_defaults(func=_plane)

    tr = s.add_parser("transform", help="rotate points about a pivot (Padathu's W = T(-P)·R·T(P)·p)")
    tr.add_argument("--rotate", action="append", default=[], metavar="AXIS:DEG",
                    help="rotation about x, y or z in degrees; repeat, applied in the order given")
    tr.add_argument("--pivot", default="0,0,0", metavar="X,Y,Z", help="P: the rotation is about -P (default 0,0,0)")
    tr.add_argument("points", nargs="*", metavar="POINTS", help="x,y,z words (put them after --) and/or CSV files")
    tr.add_argument("--json", action="store_true", help="print one JSON object")
    tr.set_defaults(func=_transform)

    rn = s.add_parser("run", help="probe top and side faces, level with A/B, find the face angle and transform")
    rn.add_argument("--sim", action="store_true", help="start the CNC simulator in-process and align its workpiece")
    rn.add_argument("--sim-config", default=None, metavar="FILE", help="simulator config (default config/sim.yaml)")
    rn.add_argument("--cell-config", default=None, metavar="FILE", help="cell config (default config/cell.yaml)")
    rn.add_argument("--cad", default=None, metavar="FILE",
                    help="CAD mesh of the part in mm, top face up (default: the sim config's workpiece)")
    rn.add_argument("--report", default=None, metavar="DIR", help="write align.json and align.png here")
    rn.add_argument("--job", default=None, metavar="JOB", help="a cell-job/1 file (CAD frame) to carry into the machine frame")
    rn.add_argument("--job-out", default=None, metavar="FILE", help="where to write it (default JOB.aligned.json)")
    rn.add_argument("--no-level", action="store_true",
                    help="a 3-axis CNC: measure the tilt and carry it in the transform, command no A/B move")
    rn.add_argument("--json", action="store_true", help="print one JSON object")
    rn.set_defaults(func=guard.command(_run))


# --- input parsing -------------------------------------------------------------------------------


def parse_triple(text: str, what: str) -> np.ndarray:
    parts = [t for t in re.split(r"[,\s]+", text.strip()) if t]
    if len(parts) != 3:
        raise InputError(f"{what} '{text}': expected three numbers X,Y,Z")
    try:
        v = np.array([float(t) for t in parts])
    except ValueError:
        raise InputError(f"{what} '{text}': expected three numbers X,Y,Z") from None
    if not np.all(np.isfinite(v)):
        raise InputError(f"{what} '{text}': values must be finite")
    return v


def _header_columns(p: Path, i: int, row: list[str]) -> tuple[int, ...] | None:
    """The x, y, z column indices named by a header row; None when the row starts with numbers."""
    try:
        [float(c) for c in row[:3]]
        return None
    except ValueError:
        pass
    names = [c.lower() for c in row]
    want = []
    for key in ("x", "y", "z"):
        cand = [j for j, nm in enumerate(names) if nm in (key, f"{key}_mm")]
        if not cand:
            raise InputError(f"{p}: line {i}: header has no '{key}' column (got {', '.join(row)})")
        want.append(cand[0])
    return tuple(want)


def _xyz(p: Path, i: int, row: list[str], cols: tuple[int, ...]) -> list[float]:
    """The finite x, y, z of one data row."""
    try:
        vals = [float(row[c]) for c in cols]
    except (ValueError, IndexError):
        raise InputError(f"{p}: line {i}: expected numbers in columns x, y, z, got {','.join(row)!r}") from None
    if not all(np.isfinite(vals)):
        raise InputError(f"{p}: line {i}: values must be finite")
    return vals


def read_points_csv(path: str | Path) -> np.ndarray:
    """x, y, z rows from a CSV (a header naming x, y, z is optional); errors name file and line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc}); check the path") from None
    rows = list(csv.reader(text.splitlines()))
    first = next((j for j, r in enumerate(rows, start=1) if any(c.strip() for c in r)), None)
    cols: tuple[int, ...] = (0, 1, 2)
    out: list[list[float]] = []
    for i, raw in enumerate(rows, start=1):
        row = [c.strip() for c in raw]
        if not any(row) or row[0].startswith("#"):
            continue
        if not out and i == first:
            header = _header_columns(p, i, row)
            if header is not None:
                cols = header
                continue
        out.append(_xyz(p, i, row, cols))
    if not out:
        raise InputError(f"{p}: no points found; expected rows of x,y,z")
    return np.array(out, dtype=float)


def _fmt(v: np.ndarray, nd: int = 6) -> str:
    return ", ".join(f"{x:.{nd}f}" for x in v)


# --- handlers ------------------------------------------------------------------------------------


def _plane(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from core.config import load_cell

    pts = read_points_csv(args.csv)
    if len(pts) < 3:
        raise InputError(f"{args.csv}: a plane needs at least 3 points, got {len(pts)}")
    cell = load_cell(args.cell_config)
    noise = cell.probe.noise_mm if args.noise is None else args.noise
    if not np.isfinite(noise) or noise < 0:
        raise InputError(f"--noise {args.noise}: must be a non-negative number of mm")
    spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    if spread[1] <= 1e-9 * max(spread[0], 1e-300):
        raise InputError(f"{args.csv}: the points are collinear; a plane needs points spread over an area")
    fit, lev = fit_and_level(pts, cell, noise_mm=noise or None, reject=not args.no_reject)
    out = {
        "normal": fit.normal.tolist(), "point": fit.point.tolist(),
        "rms_mm": fit.rms_mm, "max_residual_mm": fit.max_residual_mm,
        "outliers": list(fit.outliers), "level_a_deg": lev.a_deg, "level_b_deg": lev.second_deg,
        "n_points": fit.n_points, "chi2": None if np.isnan(fit.chi2) else fit.chi2,
        "chi2_p": None if np.isnan(fit.chi2_p) else fit.chi2_p, "chi2_ok": fit.chi2_ok,
        "tilt_deg": lev.tilt_deg,
    }
    if args.json:
        emit_json(out)
        return 0
    print(f"plane through {fit.n_points} points ({len(fit.outliers)} outlier(s) rejected: {list(fit.outliers)})")
    print(f"  normal      {_fmt(fit.normal, 8)}")
    print(f"  point       {_fmt(fit.point, 4)} mm")
    print(f"  rms         {fit.rms_mm * 1000:.2f} µm   max residual {fit.max_residual_mm * 1000:.2f} µm")
    if not np.isnan(fit.chi2):
        verdict = "consistent with" if fit.chi2_ok else "EXCEEDS"
        print(f"  χ²          {fit.chi2:.2f} on {fit.dof} dof (p = {fit.chi2_p:.3g}): {verdict} probe noise {noise * 1000:.1f} µm")
    print(f"  leveling    A = {lev.a_deg:.5f}°, B = {lev.second_deg:.5f}°  (tilt {lev.tilt_deg:.5f}°)")
    return 0


def _transform(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json

    rots = read_rotations(args.rotate)
    pivot = parse_triple(args.pivot, "--pivot")
    pts: list[np.ndarray] = []
    for word in args.points:
        if Path(word).is_file() or word.lower().endswith(".csv"):
            pts.extend(read_points_csv(word))
        else:
            pts.append(parse_triple(word, "point"))
    if not pts:
        raise InputError("no points given: put x,y,z words after -- (e.g. -- 0,0,0 1,0,0) or give a CSV file")
    m, out_pts = rotate_points(rots, pivot, np.array(pts))
    if args.json:
        emit_json({"points": out_pts.tolist(), "matrix": m.tolist(), "pivot": pivot.tolist(),
                   "rotations": [{"axis": a, "deg": d} for a, d in rots]})
        return 0
    for src, dst in zip(pts, out_pts):
        print(f"{_fmt(src, 5)}  ->  {_fmt(dst, 5)}")
    return 0


def _run(args: argparse.Namespace) -> int:
    return run_cli(args)


def _say_touch(pp: ProbedPoint) -> None:
    """Each touch on stderr as it lands (the routine takes seconds to minutes; stdout keeps the result)."""
    x, y, z = (float(v) for v in pp.position[:3])
    print(f"probed {pp.name}: {x:.4f} {y:.4f} {z:.4f} mm (spread {pp.spread_mm * 1000:.1f} µm)",
          file=sys.stderr, flush=True)


def run_cli(args: argparse.Namespace) -> int:
    """`cell align run`: probe and align on the CNC (or its simulator), print or emit JSON."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json

    cell = load_cell(args.cell_config)
    job = read_job(args.job) if getattr(args, "job", None) else None
    if job is not None and job.alignment is not None:  # refused before any probing
        raise InputError(f"{args.job}: the job already carries an alignment; a second one is refused: "
                         "align the original (unaligned) job")
    sim_path = Path(args.sim_config) if args.sim_config else None
    sim_cfg = load_sim(sim_path)
    base = sim_path.parent if sim_path else None
    plan = probe_plan_on(sim_cfg.cnc.workpiece, getattr(args, "cad", None), base)
    no_level = bool(getattr(args, "no_level", False))
    if args.sim:
        res = asyncio.run(guard.run_attached(run_with_sim(cell, sim_cfg, plan, config_dir=base, no_level=no_level,
                                                          on_point=_say_touch)))
    else:
        res = asyncio.run(guard.run_attached(align_at(cell.devices.cnc.url, cell, plan, no_level=no_level,
                                                      on_point=_say_touch)))
    out = res.to_json()
    if args.report:
        paths = write_align_report(res, args.report)
        out["report"] = {k: str(v) for k, v in paths.items()}
    if job is not None:
        dest = Path(args.job_out) if args.job_out else Path(args.job).with_suffix(".aligned.json")
        moved = aligned_job(job, res.transform, alignment_record(res))
        try:
            dest.write_text(moved.json + "\n", encoding="utf-8")
        except OSError as exc:
            raise InputError(f"{dest}: cannot write the aligned job ({exc.strerror or exc})") from None
        out["job_out"] = str(dest)
    if args.json:
        emit_json(out)
        return 0
    print(f"top plane: {res.top.n_points} points, rms {res.top_table.rms_mm * 1000:.2f} µm, "
          f"outliers {list(res.top_table.outliers)}, tilt {res.leveling.tilt_deg:.4f}°")
    print(f"leveling:  A = {res.level_a_deg:.5f}°, B = {res.level_b_deg:.5f}°  (residual tilt {res.residual_tilt_deg:.5f}°)")
    print(f"side face: {len(res.points['side'])} touches, rms {res.side.rms_mm * 1000:.2f} µm; "
          f"face angle {res.face_angle_deg:.5f}° (eq. 1: {res.face_angle_eq1_deg:.5f}°); CAD rotated to match")
    print("transform (CAD → machine at the leveled A/B):")
    for row in res.transform:
        print("  " + "  ".join(f"{v:12.6f}" for v in row))
    print(f"check: RMS distance of the touches to the moved CAD surface {res.icp_rms_mm * 1000:.2f} µm")
    if args.report:
        print(f"report: {out['report']['png']}, {out['report']['json']}")
    if job is not None:
        print(f"aligned job: {out['job_out']}")
    return 0

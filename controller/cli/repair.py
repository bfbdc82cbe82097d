"""`cell repair plan CAD --stock STOCK --width W [--allowance MM]` (docs/contract.md §4 "Repair", issue 17)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from controller.cli import guard
from controller.cli.parsing import Subcommands
from core.errors import CellError, InputError

# `cell plan` options the planner's messages may suggest that `cell repair plan` does not have
_NOT_OURS = {"--units": "the CAD's units (repair plans are in mm)", "--frame": "the frame (repair plans keep the CAD frame)",
             "--perimeters": "the perimeter count", "--five-axis": "a 5-axis plan (not available for repairs)",
             "--tilt-limit": "kinematics.tilt_limit_deg in cell.yaml"}


def _own_options(msg: str) -> str:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    import re

    return re.sub(r"--[a-z][a-z-]*(?: (?:N\|all|MM|mm\|cm\|m\|inch|substrate\|cad))?",
                  lambda m: _NOT_OURS.get(m.group(0).split()[0], m.group(0)) if m.group(0).split()[0] in _NOT_OURS
                  else m.group(0), msg)


def register(sub: Subcommands) -> None:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.plan import fraction_arg, positive_arg
    from controller.cli.runargs import add_trace_args

    p = sub.add_parser("repair", help="hybrid repair: plan the missing volume of a part, and run it",
                       description="Plan a repair: nominal CAD minus the machined stock (+ allowance), "
                                   "in the CAD frame.")
    rs = p.add_subparsers(dest="repair_command", metavar="SUBCOMMAND")
    rs.required = True
    pl = rs.add_parser("plan", help="plan the repair volume (CAD − stock + allowance) in the CAD frame")
    pl.add_argument("cad", metavar="CAD", help="nominal part (STL/OBJ/3MF), in its CAD frame")
    pl.add_argument("--stock", required=True, metavar="STOCK", help="the machined part as a mesh, in the CAD frame")
    pl.add_argument("--width", type=positive_arg, required=True, metavar="W", help="bead width, mm")
    pl.add_argument("--allowance", type=float, default=0.0, metavar="MM",
                    help="finishing allowance added on top of the repaired surfaces, mm (default 0)")
    pl.add_argument("--overhang", type=float, default=None, metavar="MM",
                    help="carry the repair this far beyond the part's free edges, to machine back "
                         "(default: half the bead width; 0: stop at the outline; docs/repair.md)")
    pl.add_argument("--material", metavar="M", help="material name or YAML file (default: cell.yaml's)")
    pl.add_argument("--layer-height", type=positive_arg, metavar="H", help="layer height, mm (default: the bead height)")
    pl.add_argument("--min-coverage", type=fraction_arg, default=0.97, metavar="F",
                    help="every layer at least this share covered by beads (default 0.97)")
    pl.add_argument("--allow-overhang", action="store_true",
                    help="plan steps out beyond the overhang rule anyway, with a warning")
    pl.add_argument("--allow-underfill", action="store_true",
                    help="plan a feature no legal bead fills (or a layer below 97 %% coverage) anyway, with a warning")
    pl.add_argument("--out", metavar="JOB", help="job file (default: STEM.repair.job.json here)")
    pl.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    pl.set_defaults(func=run_plan)
    rr = rs.add_parser("run", help="probe, level, align, deposit, probe again, report: the whole repair chain")
    rr.add_argument("job", metavar="JOB", help="the repair job `cell repair plan` wrote (CAD frame, no alignment)")
    rr.add_argument("--sim", action="store_true", help="run against the simulators in this process")
    rr.add_argument("--sim-config", metavar="FILE", help="simulator config (default config/sim.yaml): the stock "
                    "mesh and its pose on the table")
    rr.add_argument("--cell-config", metavar="FILE", help="cell.yaml (default config/cell.yaml)")
    rr.add_argument("--runs", metavar="DIR", help="runs directory (default: cell.yaml's runs_dir)")
    rr.add_argument("--log", metavar="DIR", help="with --sim: the simulators' logs (deposit.jsonl, cnc.jsonl)")
    rr.add_argument("--tolerance", type=float, default=0.1, metavar="MM",
                    help="verify: height error beyond this is a defect (default 0.1 mm)")
    rr.add_argument("--no-finish", action="store_true",
                    help="deposit and verify against the plan only: no stock probe, no machining (docs/machining.md)")
    rr.add_argument("--json", action="store_true", help="print the report as one JSON object")
    add_trace_args(rr)
    rr.set_defaults(func=guard.command(run_repair))


def _load(path: str, what: str) -> Any:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    import trimesh

    if not Path(path).is_file():
        raise InputError(f"{what} {path}: no such file")
    try:
        return trimesh.load_mesh(path, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for a bad file
        raise InputError(f"{what} {path}: cannot read the mesh ({exc})") from None


def run_plan(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.api.jobs import repair_volume
    from controller.cli.plan import material_named
    from planner.job import job_to_dict
    from planner.plan import PlanOptions, plan_part

    cad, stock = _load(args.cad, "CAD"), _load(args.stock, "--stock")
    overhang = args.width / 2 if args.overhang is None else args.overhang
    rv = repair_volume(cad, stock, args.allowance, cad_name=args.cad, stock_name=args.stock, overhang_mm=overhang)
    opt = PlanOptions(width_mm=args.width, frame="cad", layer_height_mm=args.layer_height,
                      min_coverage=args.min_coverage, allow_overhang=args.allow_overhang,
                      allow_underfill=args.allow_underfill)
    try:
        job = plan_part(rv.mesh, opt, material_named(args.material))
    except CellError as exc:  # the planner's advice names `cell plan` options: only ours are named
        try:
            again = type(exc)(_own_options(str(exc)))
        except TypeError:
            again = InputError(_own_options(str(exc)))
        raise again from None
    d = job_to_dict(job)
    d["source"]["file"] = Path(args.cad).name
    # stored resolved: `cell repair run` finds them from any directory (load_cad also tries the job's)
    d["repair"] = {"cad": str(Path(args.cad).resolve()), "stock": str(Path(args.stock).resolve()),
                   "allowance_mm": args.allowance, "overhang_mm": overhang,
                   "overhang_mm3": round(rv.overhang_mm3, 3),
                   "volume_mm3": round(rv.volume_mm3, 3), "bounds_mm": rv.bounds.round(4).tolist()}
    out = Path(args.out) if args.out else Path(Path(args.cad).stem + ".repair.job.json")
    try:
        out.write_text(json.dumps(d, sort_keys=True) + "\n", encoding="utf-8")
    except OSError as exc:
        raise InputError(f"--out {out}: cannot write the job file ({exc.strerror or exc})") from None
    js = job.summary or {}
    summary = {"volume_mm3": round(rv.volume_mm3, 3), "layers": len(job.layers),
               "passes": sum(len(L.passes) for L in job.layers),
               "arc_starts": int(js.get("arc_starts", sum(len(L.passes) for L in job.layers))),
               "coverage": js.get("coverage"), "frame": "cad", "job": str(out),
               "repair_volume_mm3": round(rv.volume_mm3, 3), "bounds_mm": rv.bounds.round(3).tolist(),
               "overhang_mm3": round(rv.overhang_mm3, 3), "warnings": list(js.get("warnings", []))}
    if args.json:
        emit_json(summary)
    else:
        print(f"repair volume {summary['repair_volume_mm3']} mm³ between {summary['bounds_mm'][0]} and "
              f"{summary['bounds_mm'][1]} mm (CAD frame): {summary['layers']} layers, {summary['passes']} passes")
        print(f"job: {out}")
    return 0


def run_repair(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    import asyncio

    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.cli.runargs import with_trace
    from controller.api.jobs import read_job
    from controller.harness import repair_run_devices, repair_run_sim
    from core.config import load_cell, load_sim

    path = Path(args.job)
    job = read_job(path)
    cell = with_trace(load_cell(args.cell_config), args)
    sim_cfg = load_sim(Path(args.sim_config) if args.sim_config else None) if args.sim else None
    if sim_cfg is not None and args.sim_config:
        wp = sim_cfg.cnc.workpiece
        if wp.mesh and not Path(wp.mesh).is_absolute():  # a mesh named next to the sim config
            mesh = Path(args.sim_config).parent / wp.mesh
            sim_cfg = sim_cfg.model_copy(update={"cnc": sim_cfg.cnc.model_copy(update={
                "workpiece": wp.model_copy(update={"mesh": str(mesh)})})})
    runs = args.runs or cell.cell.runs_dir
    if sim_cfg is not None:
        rep = asyncio.run(repair_run_sim(job, cell, sim_cfg, job_path=path, runs_dir=runs, log_dir=args.log,
                                         tolerance_mm=args.tolerance, finish=not args.no_finish))
    else:
        # `cell sim up` or hardware: the simulators' clock lowered for the build where the host cannot
        # feed it at cell.yaml's time scale, said before any motion (docs/controller.md)
        rep = asyncio.run(repair_run_devices(job, cell, job_path=path, runs_dir=runs, tolerance_mm=args.tolerance,
                                             finish=not args.no_finish,
                                             say=lambda m: print(m, file=sys.stderr, flush=True)))
    if args.json:
        emit_json(rep)
        return 1 if rep["verify"]["defects"] else 0   # docs/repair.md: a verify defect exits 1, either way
    a, v = rep["alignment"], rep["verify"]
    print(f"aligned: A {a['level_a_deg']}°, B {a['level_b_deg']}°, face angle {a['face_angle_deg']}°")
    print(f"built: {rep['build']['state']}, {rep['build']['passes_done']} passes ({rep['build']['run_dir']})")
    if "machining" in rep:
        st, mc = rep["stock"], rep["machining"]
        print(f"stock: {st['min_mm']}…{st['max_mm']} mm above CAD at {st['points']} touches")
        print(f"machined: {mc['tool']}, {mc['removal_mm3']} mm³ removed, {mc['time_s']} s")
    against = "CAD" if "machining" in rep else f"the plan (vs CAD + allowance {v.get('vs_nominal_mean_mm')} mm)"
    print(f"verify against {against}: {v['points']} touches, height error mean {v['height_error_mean_mm']} mm, max "
          f"{v['height_error_max_mm']} mm, flatness {v['flatness_mm']} mm; defects: {len(v['defects'])}")
    return 1 if v["defects"] else 0


def demo_repair(args: argparse.Namespace) -> int:
    """`cell demo --repair`: a 100×100×20 block with a 20×20×4 pocket in one corner, mounted tilted
    1.2°/−0.8°, turned 3° and shifted; planned, aligned, deposited and verified on the simulators."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    import asyncio
    import time

    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.jobs import read_job, repair_volume
    from controller.harness import make_parts, posed_sim, repair_run_sim, with_urls
    from controller.cli.main import emit_json
    from controller.cli.runargs import with_trace
    from core.config import load_cell, load_material
    from planner.job import job_to_dict
    from planner.plan import PlanOptions, plan_part

    cell = with_trace(load_cell(), args)
    runs = Path(args.runs or cell.cell.runs_dir)
    work = runs / time.strftime("repair-demo-%Y%m%d-%H%M%S")
    work.mkdir(parents=True, exist_ok=True)
    cad, stock = make_parts(work)
    rv = repair_volume(_load(str(cad), "CAD"), _load(str(stock), "--stock"), 0.3)
    job = job_to_dict(plan_part(rv.mesh, PlanOptions(width_mm=4.0, frame="cad"), load_material(cell.cell.material)))
    job = json.loads(json.dumps(job))
    job["repair"] = {"cad": str(cad), "stock": str(stock), "allowance_mm": 0.3,
                     "volume_mm3": round(rv.volume_mm3, 3), "bounds_mm": rv.bounds.round(4).tolist()}
    (work / "repair.job.json").write_text(json.dumps(job) + "\n", encoding="utf-8")
    typed = read_job(work / "repair.job.json")
    # the power source's 100 ms watchdog on a loaded machine: the repair is short, no need to race
    cell = with_urls(cell, {}, time_scale=min(float(args.time_scale), 40.0))
    rep = asyncio.run(repair_run_sim(typed, cell, posed_sim(stock, 1.2, -0.8, 3.0, (2.0, -1.5, 0.5)),
                                     job_path=work / "repair.job.json", runs_dir=work / "runs", log_dir=work / "sim"))
    rep["work_dir"] = str(work)
    if args.json:
        emit_json(rep)
    else:
        a, v = rep["alignment"], rep["verify"]
        print(f"repair demo in {work}: pocket {rv.volume_mm3:.0f} mm³ planned in the CAD frame")
        print(f"aligned: A {a['level_a_deg']}°, B {a['level_b_deg']}°, face angle {a['face_angle_deg']}° "
              "(the stock is mounted at 1.2°, -0.8°, 3°)")
        print(f"built: {rep['build']['state']}; verify: height error mean {v['height_error_mean_mm']} mm, max "
              f"{v['height_error_max_mm']} mm, flatness {v['flatness_mm']} mm; defects {len(v['defects'])}")
    return 0 if rep["build"]["state"] == "complete" and not rep["verify"]["defects"] else 1

"""`cell finish plan RUN_DIR|JOB [--tool T] [--out PROGRAM]`: finish a near-net build's top faces.

The stock is the plan's model of the deposit (each layer's passes widened by their width, at the
layer's z), the target the job's own CAD (a repair job's `repair.cad`, else the planned mesh
`source.file` in the job's frame); the region the CAD's top faces. Planned as the repair's
machining is (planner/finish.py, docs/machining.md); `--out` writes the milling program (machine
frame = the job's frame), with the tool change for `--firmware grblhal` (T M6) or `grbl` (M0 pause).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from controller.cli.parsing import Subcommands
from core.errors import InputError


def register(sub: Subcommands) -> None:
    fp = sub.add_parser("finish", help="finish machining plans (docs/machining.md)")
    fs = fp.add_subparsers(dest="finish_cmd", required=True)
    p = fs.add_parser("plan", help="rough and finish a near-net build's top faces to its CAD")
    p.add_argument("source", metavar="RUN_DIR|JOB", help="a job file, or a run directory holding one")
    p.add_argument("--tool", metavar="T", help="a cutter of cell.yaml tools.cutters (default machining.cutter)")
    p.add_argument("--out", metavar="PROGRAM", help="write the milling program (G-code) here")
    p.add_argument("--firmware", choices=("grblhal", "grbl"), default="grblhal",
                   help="the tool change the program carries (default grblhal: T M6)")
    p.add_argument("--cell-config", metavar="FILE", help="cell.yaml (default config/cell.yaml)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(func=run_finish_plan)


def _job_path(source: str) -> Path:
    p = Path(source)
    if p.is_dir():
        found = sorted(p.glob("*.json"))
        jobs = [f for f in found if f.name.endswith("job.json")] or [f for f in found if f.name == "job.json"]
        if not jobs:
            raise InputError(f"{p}: no job file (*job.json) in this run directory; give the job file")
        return jobs[0]
    if not p.is_file():
        raise InputError(f"{p}: no such job file or run directory")
    return p


def job_cad(job: Any, path: Path) -> np.ndarray:
    """The job's CAD triangles in the job's frame: a repair job's `repair.cad`, else `source.file`."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.jobs import repair_mesh
    from planner.mesh import read_mesh

    if job.repair is not None and job.repair.cad:
        cad: np.ndarray = np.asarray(repair_mesh(job, path).triangles, dtype=float)
        return cad
    src = Path(job.job.source.file)
    if not src.is_absolute():
        src = path.parent / src
    if not src.is_file():
        raise InputError(f"{path}: source.file {job.job.source.file}: no such mesh; put the planned mesh there")
    pm = read_mesh(src, job.job.source.units)
    tri: np.ndarray = np.asarray(pm.vertices, dtype=float)[np.asarray(pm.faces)].copy()
    if job.job.frame == "cad":
        tri[:, :, 2] += pm.z_shift_mm
    return tri


def run_finish_plan(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.api.jobs import read_job
    from controller.api.programs import finish_top, milling_program
    from core.config import load_cell

    path = _job_path(args.source)
    job = read_job(path)
    cell = load_cell(args.cell_config)
    fin = finish_top(job, job_cad(job, path), cell, args.tool, str(path))
    out = {**fin.summary(), "job": str(path)}
    if args.out:
        lines = milling_program(fin, args.firmware)
        Path(args.out).write_text("\n".join(lines) + "\n", encoding="utf-8")
        out.update(out_file=str(args.out), lines=len(lines))
    if args.json:
        emit_json(out)
    else:
        print(json.dumps(out))
    return 0

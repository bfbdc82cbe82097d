"""`cell export JOB --format gcode|rapid|krl [--out FILE] [--json]` (docs/contract.md §7)."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from core.errors import InputError


def register(sub: Any) -> None:
    p = sub.add_parser("export", help="write the job as a G-code, ABB RAPID or KUKA KRL program",
                       description="Export a job file as a program a CNC or robot controller runs itself.")
    p.add_argument("job", metavar="JOB", help="the job file (cell-job/1)")
    p.add_argument("--format", required=True, choices=("gcode", "rapid", "krl"), help="program format")
    p.add_argument("--out", metavar="FILE", help="file to write (default: JOB's stem + .nc/.mod/.src)")
    p.add_argument("--cell-config", metavar="FILE", help="cell.yaml (clearance, travel speed)")
    p.add_argument("--json", action="store_true", help="print format, out, lines, passes as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from core.config import load_cell
    from controller.export import SUFFIX, export_job
    from controller.job.read import read_job

    job = read_job(args.job)
    cfg = load_cell(args.cell_config) if args.cell_config else load_cell()
    stem = Path(args.job).name.removesuffix(".json").removesuffix(".job")
    out = Path(args.out) if args.out else Path(stem + SUFFIX[args.format])
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.motion.kinematics import Trunnion

    res = export_job(job, args.format, name=stem, out=out, clearance_mm=cfg.limits.clearance_mm,
                     travel_mm_min=cfg.limits.travel_speed_mm_min, trunnion=Trunnion.from_config(cfg.kinematics),
                     baud=cfg.devices.cnc.baud)
    for path, lines in res.files.items():
        try:
            Path(path).write_text("\n".join(lines) + "\n", encoding="ascii")
        except OSError as exc:
            raise InputError(f"{path}: cannot write the program ({exc.strerror or exc}); check --out") from None
    if args.json:
        emit_json({"format": res.format, "out": list(res.files)[0], "files": list(res.files),
                   "lines": res.lines, "passes": res.passes})
    else:
        for path, lines in res.files.items():
            print(f"{path}: {len(lines)} lines")
        print(f"{res.passes} passes as {res.format}")
    return 0

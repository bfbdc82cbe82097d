"""`cell export JOB --format gcode|rapid|krl [--out FILE] [--json]` (docs/contract.md §7).

`--finish` (G-code only): the milling program of the job's top faces beside the deposition program,
`<out stem>.finish.nc` (controller/export/milling.py, docs/machining.md), in the same frame: the
job's alignment applied when it carries one."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from controller.cli.parsing import Subcommands
from core.errors import InputError


def register(sub: Subcommands) -> None:
    p = sub.add_parser("export", help="write the job as a G-code, ABB RAPID or KUKA KRL program",
                       description="Export a job file as a program a CNC or robot controller runs itself.")
    p.add_argument("job", metavar="JOB", help="the job file (cell-job/1)")
    p.add_argument("--format", required=True, choices=("gcode", "rapid", "krl"), help="program format")
    p.add_argument("--out", metavar="FILE", help="file to write (default: JOB's stem + .nc/.mod/.src)")
    p.add_argument("--cell-config", metavar="FILE", help="cell.yaml (clearance, travel speed)")
    p.add_argument("--finish", action="store_true",
                   help="gcode: also write the milling program of the top faces (OUT stem + .finish.nc)")
    p.add_argument("--tool", metavar="T", help="with --finish: a cutter of tools.cutters (default machining.cutter)")
    p.add_argument("--firmware", choices=("grblhal", "grbl"), default="grblhal",
                   help="with --finish: the tool change the program carries (default grblhal: T M6)")
    p.add_argument("--json", action="store_true", help="print format, out, lines, passes as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from core.config import load_cell
    from controller.api.jobs import read_job
    from controller.api.programs import SUFFIX, export_program

    if args.finish and args.format != "gcode":
        raise InputError(f"--finish: a milling program is G-code; give --format gcode (not {args.format})")
    job = read_job(args.job)
    cfg = load_cell(args.cell_config) if args.cell_config else load_cell()
    stem = Path(args.job).name.removesuffix(".json").removesuffix(".job")
    out = Path(args.out) if args.out else Path(stem + SUFFIX[args.format])
    res = export_program(job, args.format, name=stem, out=out, cfg=cfg)
    files = dict(res.files)
    finish = _finish(args, job, cfg, out) if args.finish else None
    if finish is not None:
        files[finish["out"]] = finish.pop("program")
    for path, lines in files.items():
        try:
            Path(path).write_text("\n".join(lines) + "\n", encoding="ascii")
        except OSError as exc:
            raise InputError(f"{path}: cannot write the program ({exc.strerror or exc}); check --out") from None
    if args.json:
        emit_json({"format": res.format, "out": list(res.files)[0], "files": list(files),
                   "lines": res.lines, "passes": res.passes, **({"finish": finish} if finish is not None else {})})
    else:
        for path, lines in files.items():
            print(f"{path}: {len(lines)} lines")
        print(f"{res.passes} passes as {res.format}")
        if finish is not None:
            print(f"milling: {finish['tool']}, {finish['passes']} passes, scallop {finish['scallop_mm']} mm")
    return 0


def _finish(args: argparse.Namespace, job: Any, cfg: Any, out: Path) -> dict[str, Any]:
    """The milling program of the job's top faces, in the deposition program's frame."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.finish import job_cad
    from controller.api.programs import alignment_matrix, finish_top, milling_program, points_in_machine_frame

    if points_in_machine_frame(job):
        raise InputError(f"{args.job}: --finish: the job's points were moved to the machine frame (an older "
                         "`cell align run --job`); export the job `cell plan` wrote, with its alignment beside it")
    fin = finish_top(job, job_cad(job, Path(args.job)), cfg, args.tool, str(args.job))
    lines = milling_program(fin, args.firmware, alignment_matrix(job))
    path = out.with_name(out.name.removesuffix(out.suffix) + ".finish.nc")
    return {**fin.summary(), "out": str(path), "lines": len(lines), "firmware": args.firmware, "program": lines}

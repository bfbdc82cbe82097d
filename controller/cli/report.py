"""`cell report RUN_DIR [--csv FILE]` and `cell runs`: the build record, from the journal alone,
through the controller's API (controller/api/ `write_run_report`, `run_rows`)."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from controller.cli.parsing import Subcommands


def register(sub: Subcommands) -> None:
    p = sub.add_parser("report", help="write and print a run's build record (report.json, CSV, plots)")
    p.add_argument("run_dir", metavar="RUN_DIR")
    p.add_argument("--csv", metavar="FILE", help="also write one row per bead here (default RUN_DIR/beads.csv)")
    p.add_argument("--operator", help="operator's name for the record")
    p.add_argument("--no-plots", action="store_true", help="skip the PNGs")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_report)
    r = sub.add_parser("runs", help="one row per run in the runs directory")
    r.add_argument("--runs", metavar="DIR", help="runs directory (default: cell.yaml's runs_dir)")
    r.add_argument("--cell-config", metavar="FILE")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=_runs)


def _report(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api import write_run_report
    from controller.cli.main import emit_json

    path = write_run_report(Path(args.run_dir), plots=not args.no_plots, operator=args.operator, csv_path=args.csv)
    rep = json.loads(path.read_text(encoding="utf-8"))
    summary = {k: v for k, v in rep.items() if k not in ("beads", "layers", "per_layer")}
    summary["report"] = str(path)
    summary["beads"] = len(rep["beads"])
    if args.json:
        emit_json(summary)
        return 0
    a = rep["arc_time_figures"]
    print(f"{rep['job']['name']}: {rep['state']}, layers {rep['layers_done']}/{rep['layers_total']}, "
          f"passes {rep['passes_done']}/{rep['passes_total']}, {rep['started']} .. {rep['ended']}")
    ts = rep.get("travel_speed") or {}
    print(f"arc time: plan {a['plan_s']} s, deposited at planned speed {a['planned_s']} s, at measured speed "
          f"{a['measured_s']} s ({'agree' if a['agree'] else 'DISAGREE'} within 2 %); source arc-on {a['arc_on_s']} s")
    if ts.get("beads_measured"):
        print(f"travel speed: worst bead {100 * ts['worst_deviation']:+.1f} % from plan, "
              f"{ts['starved_beads']} bead(s) with the motion queue run empty")
    print(f"wire lot {rep.get('wire_lot') or '-'}, gas {rep.get('gas') or '-'}, operator {rep.get('operator') or '-'}")
    print(f"report: {path}; csv: {rep['csv']} ({len(rep['beads'])} beads)")
    return 0


def _runs(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api import run_rows
    from controller.cli.main import emit_json
    from core.config import load_cell

    runs = Path(args.runs) if args.runs else Path(load_cell(args.cell_config).cell.runs_dir)
    rows = run_rows(runs) if runs.is_dir() else []
    if args.json:
        emit_json({"runs_dir": str(runs), "runs": rows})
        return 0
    for r in rows:
        print(f"{r['dir']}  {r['job']}  {r['state']}  {r['started']}  layers {r['layers_done']}/{r['layers_total']}  "
              f"lot {r['wire_lot'] or '-'}  operator {r['operator'] or '-'}")
    if not rows:
        print(f"no runs in {runs}")
    return 0

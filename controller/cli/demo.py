"""`cell demo`: simulators up, plan the demo part, probe and align the substrate, build it at the
demo's time scale, write the report, print the summary (`--repair`: the hybrid repair demo).

Exit status as `cell run` (controller/cli/run.py): 0 complete, 1 stopped, 2 bad input, 3 complete
with defects, 130 / 143 / 129 stopped by a signal.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import time
from pathlib import Path
from typing import Any, Callable

from controller.cli import guard, runargs
from controller.cli.run import drive, err_line, out_line, print_summary, exit_code
from controller.cli.parsing import Subcommands
from controller.api.jobs import CellJob
from controller.defaults import DEMO_MAX_STEP_MM, DEMO_PART, DEMO_TIME_SCALE, DEMO_WIDTH_MM
from core.config import CellConfig, load_cell, load_sim
from core.errors import CellError


def register(sub: Subcommands) -> None:
    d = sub.add_parser("demo", help="the demo: simulators, plan, align, build, report")
    d.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    d.add_argument("--time-scale", type=float, default=DEMO_TIME_SCALE, help=argparse.SUPPRESS)
    d.add_argument("--layers", type=int, default=None, help=argparse.SUPPRESS)  # quick demo in tests
    d.add_argument("--runs", default=None, metavar="DIR", help="runs directory (default cell.yaml's runs_dir)")
    d.add_argument("--no-align", action="store_true", help="skip probing and aligning the substrate")
    d.add_argument("--process-control", choices=("open", "layer"), default=None,
                   help="closed-loop layer height for the demo (default cell.yaml's process_control.mode)")
    d.add_argument("--no-feed-forward", action="store_true",
                   help="plan the demo with one speed per bead (no per-segment feed-forward: docs/along-the-path.md)")
    d.add_argument("--repair", action="store_true",
                   help="hybrid repair instead: a block with a milled pocket, posed on the CNC table, "
                        "repaired end to end (cell repair run --sim)")
    runargs.add_trace_args(d)
    d.set_defaults(func=guard.command(_demo))


def _demo(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.jobs import check_job_for_cell, job_from_dict, run_dir_for
    from controller.harness import with_urls
    from core.config import load_material
    from planner.job import job_to_dict
    from planner.plan import PlanOptions, plan_part

    if getattr(args, "repair", False):
        # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
        from controller.cli.repair import demo_repair

        return demo_repair(args)
    say = err_line if args.json else out_line
    t0 = time.monotonic()
    cfg = runargs.with_trace(load_cell(), args)
    cfg = with_urls(cfg, {}, time_scale=args.time_scale)
    if getattr(args, "process_control", None):  # docs/closed-loop.md
        cfg = cfg.model_copy(update={"process_control": cfg.process_control.model_copy(update={"mode": args.process_control})})
    mat = load_material(cfg.cell.material)
    say(f"planning {DEMO_PART.name}: {DEMO_WIDTH_MM} mm beads of {mat.name}, perimeters until they meet (Fang 2019)")
    plan = plan_part(str(DEMO_PART), PlanOptions(width_mm=DEMO_WIDTH_MM, perimeters="all",
                                                 feed_forward=not getattr(args, "no_feed_forward", False)), mat)
    planned = json.loads(json.dumps(job_to_dict(plan)))   # the job file's object, as `cell plan` writes it
    if args.layers:   # the job file's own layers cut (its hash is of what is built)
        planned["layers"] = planned["layers"][: args.layers]
    job = job_from_dict(planned, f"demo job ({DEMO_PART.name})")
    check_job_for_cell(job, cfg, f"demo job ({DEMO_PART.name})")
    s = job.job.summary
    say(f"  {len(job.layers)} layers, {job.passes_total} beads, "
        f"{s.get('deposit_length_mm', 0) / 1000:.1f} m of bead, {s.get('arc_time_s', 0) / 60:.1f} min of arc, "
        f"about {s.get('est_time_s', 0) / 60:.0f} min with travel and interpass waits")
    runs = Path(args.runs or cfg.cell.runs_dir)
    run_dir = run_dir_for(job, runs)
    if (run_dir / "journal.sqlite").exists():
        # a fresh demo each time: keep the old one beside it
        old = run_dir.with_name(run_dir.name + time.strftime("-%Y%m%d-%H%M%S"))
        run_dir.rename(old)
    ctl, align = asyncio.run(_demo_cell(cfg, job, run_dir, runs, say, not args.no_align))
    out = ctl.result_json
    out["alignment"] = align
    out["wall_time_s"] = round(time.monotonic() - t0, 1)
    if args.json:
        # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
        from controller.cli.main import emit_json

        emit_json(out)
    else:
        print_summary(out, say)
        say(f"run directory: {out['run_dir']} (journal.sqlite, report.json, layers.png, process.png, "
            f"temperature.png, defects.png); {out['wall_time_s']} s wall")
    return exit_code(out)


async def _demo_cell(cfg: CellConfig, job: CellJob, run_dir: Path, runs: Path, say: Callable[[str], None],
                     do_align: bool) -> tuple[Any, dict[str, Any] | None]:
    """The demo's cell: the simulators in a process of their own, as real devices are (`cell sim
    up`, controller/harness/cell.py); aligned, built; the API object and the alignment."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.types import BuildOptions
    from controller.harness import open_cell

    async with open_cell(cfg, sim=True, process=True, log_dir=run_dir / "sim", runs_dir=runs, connect=False) as ctl:
        assert ctl.simulators is not None
        say(f"simulators up (`cell sim up`, pid {ctl.simulators.process_id}) at time scale {cfg.cell.time_scale:g} "
            f"(process time {cfg.cell.time_scale:g}x wall time)")
        ctl.options = BuildOptions(**{**ctl.options.__dict__, "max_step_mm": DEMO_MAX_STEP_MM})
        _res, _report, align = await _demo_drive(ctl, job, say, do_align)
    return ctl, align


async def _demo_drive(ctl: Any, job: CellJob, say: Callable[[str], None],
                      do_align: bool) -> tuple[Any, Path | None, dict[str, Any] | None]:
    align = None
    guard.attach(None, say)  # a signal while aligning: cancelled, the CNC safe-stopped (run_on_url)
    if do_align:
        align = await _align(ctl, say)
    res, report = await drive(ctl, job, None, [], say, False)
    if align is not None and report is not None:
        rep = json.loads(report.read_text(encoding="utf-8"))
        rep["alignment"] = align
        report.write_text(json.dumps(rep, indent=2) + "\n", encoding="utf-8")
        if ctl.cfg.records.url:   # the store's copy is the run directory's (docs/records.md)
            # lazy: the records room loads only for a cell with a store
            from controller.api.records import resend_record

            await asyncio.to_thread(resend_record, report.parent, ctl.cfg.records.url, cell=ctl.cfg.cell.name,
                                    timeout_s=ctl.cfg.records.connect_timeout_s)
    return res, report, align


async def _align(ctl: Any, say: Callable[[str], None]) -> dict[str, Any] | None:
    """Probe and align the substrate over the CNC link."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api import align_at
    from controller.api.geometry import probe_plan_on

    cfg = ctl.cfg
    sim_cfg = ctl.simulators.sim_cfg if ctl.simulators is not None else load_sim()
    say("probing and aligning the substrate on the CNC (touch probe, G38.2)...")
    try:
        plan = probe_plan_on(sim_cfg.cnc.workpiece)
        res = await asyncio.wait_for(align_at(cfg.devices.cnc.url, cfg, plan), 60.0)
    except (CellError, asyncio.TimeoutError) as exc:
        say(f"alignment failed: {exc or 'timed out'}; building without it")
        return {"error": str(exc) or "timed out"}
    out = {"level_a_deg": round(res.level_a_deg, 5), "level_b_deg": round(res.level_b_deg, 5),
           "face_angle_deg": round(res.face_angle_deg, 5), "transform": res.transform.tolist()}
    say(f"  leveling A {out['level_a_deg']}°, B {out['level_b_deg']}°, face angle {out['face_angle_deg']}°")
    return out

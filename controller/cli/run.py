"""`cell run JOB`, `cell resume`, `cell demo`: build a job on the cell (or its simulators).

- `cell run JOB [--sim] [--fault SPEC] [--json]`: without `--sim` the devices of cell.yaml
  (real ones, or `cell sim up`); with it, every simulator starts in this process.
- `cell resume [RUN_DIR] [--sim] [--json]`: after a crash or a fault, reconnect, reset, and
  continue the build of the latest (or the given) run directory from its journal.
- `cell demo [--json]`: simulators up, plan the demo part, probe and align the substrate,
  build it at the demo's time scale, write the report, print the summary.

Exit status: 0 when the build completed, 1 when it stopped (fault, E-stop, abort), 2 on bad
input or an unreachable device (one `error:` line), 3 when it completed with defects (beads the
devices' measurements say were not deposited as planned: docs/controller.md), 130 / 143 / 129 when
SIGINT / SIGTERM / SIGHUP stopped it on the fault path (controller/cli/guard.py).
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import re
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from core.config import CellConfig, SimConfig, load_cell, load_sim
from controller.cli import guard, outcome, runargs
from controller.cli.pause_prompt import PausePrompt
from controller.cli.parsing import Subcommands
from controller.api.jobs import CellJob, check_job_for_cell, complete_in, read_job
from controller.api.runs import check_free_space
from core.errors import CellError, InputError

from controller.defaults import (  # noqa: F401  (the demo's figures live with the controller)
    DEMO_MAX_STEP_MM, DEMO_PART, DEMO_TIME_SCALE, DEMO_WIDTH_MM, SIM_REPLY_TIMEOUT_MS, sim_reply_timeout_ms,
)

if TYPE_CHECKING:
    from controller.harness import FedScale

SCENARIO_FAULTS = ("arc_loss", "wire_stick")  # `name@layer=N` is driven by the controller's sim harness


def register(sub: Subcommands) -> None:
    p = sub.add_parser("run", help="build a job on the cell (or on its simulators with --sim)")
    p.add_argument("job", metavar="JOB", help="job file (cell-job/1 JSON, from `cell plan`)")
    _common(p)
    p.add_argument("--reset-errors", action="store_true",
                   help="before motion, clear an error the power source still has latched (journaled)")
    p.add_argument("--fault", metavar="SPEC", default=None,
                   help="seeded fault spec for the simulators, e.g. 'seed=7,corrupt=0.01,arc_loss@layer=3' (--sim)")
    p.add_argument("--new", action="store_true",
                   help="build the job again in a new run directory even if the runs directory holds it complete")
    p.set_defaults(func=guard.command(_run))
    r = sub.add_parser("resume", help="continue an interrupted build from its journal")
    r.add_argument("run_dir", metavar="RUN_DIR", nargs="?", default=None,
                   help="run directory (default: the latest under runs/)")
    _common(r)
    r.set_defaults(func=guard.command(_resume))


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sim", action="store_true", help="start every simulator in this process")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.add_argument("--cell-config", default=None, metavar="FILE", help="cell config (default config/cell.yaml)")
    p.add_argument("--sim-config", default=None, metavar="FILE", help="simulator config with --sim")
    p.add_argument("--runs", default=None, metavar="DIR", help="runs directory (default cell.yaml's runs_dir)")
    p.add_argument("--max-step", type=runargs.max_step, default=2.0, metavar="MM",
                   help="split weld moves to at most this length (bounds the re-arc overlap; default 2)")
    p.add_argument("--sim-log", default=None, metavar="DIR",
                   help="with --sim: write the simulators' logs here (default RUN_DIR/sim)")
    runargs.add_trace_args(p)


# -- helpers -------------------------------------------------------------------------------------


def split_faults(spec: str | None) -> tuple[str, list[tuple[str, int, float | None]]]:
    """The spec for the simulators, and the `name@layer=N` scenarios the harness drives."""
    if not spec:
        return "", []
    keep, scen = [], []
    for part in (x.strip() for x in spec.split(",")):
        m = re.fullmatch(r"(\w+)@layer=(\d+)(?::([\d.]+)(ms|s)?)?", part)
        if m and m.group(1) in SCENARIO_FAULTS:
            dur = None
            if m.group(3):
                dur = float(m.group(3)) / (1000.0 if m.group(4) == "ms" else 1.0)
            scen.append((m.group(1), int(m.group(2)), dur))
        elif part:
            keep.append(part)
    # lazy: the simulators' modules load only for a build that asks for faults
    from controller.harness import check_fault_spec

    check_fault_spec(",".join(keep))  # a bad key or value: ConfigError naming it
    return ",".join(keep), scen


async def _scenario(ctl: Any, harness: Any, scen: list[tuple[str, int, float | None]]) -> None:
    """Inject `name@layer=N` faults in the middle of the first bead of the job's layer index N
    (the `index` of the job file, as the alarms report it)."""
    for name, layer, dur in scen:
        while True:
            s = ctl.snapshot()
            if s.layer is not None and s.layer >= layer and s.state == "running_depositing":
                break
            if s.state in ("complete", "aborted", "fault", "estop"):
                return
            await asyncio.sleep(0.005)
        await asyncio.sleep(0.05)
        harness.inject("power_source", name, duration_s=(0.5 if dur is None else dur) if name == "arc_loss" else None)


class Progress:
    """Progress lines on stderr (stdout stays for --json)."""

    def __init__(self, out: Callable[[str], None]) -> None:
        # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
        from controller.api.types import ProgressPrinter

        self.t0 = time.monotonic()
        self.printer = ProgressPrinter(lambda line: out(f"[{time.monotonic() - self.t0:6.1f} s] {line}"))

    def __call__(self, snap: Any) -> None:
        self.printer(snap)


def err_line(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()
    outcome.error(line)


def out_line(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _result_json(ctl: Any, res: Any, report: Path | None) -> dict[str, Any]:
    alarms = []
    if ctl.journal is not None:
        for a in ctl.journal.alarm_rows():
            alarms.append({"message": a["message"], "kind": a["state"], "layer": a["layer"], "pass": a["pass"],
                           "position": a["position"]})
    defects = []
    if ctl.journal is not None:
        defects = [{"layer": d["layer"], "pass": d["pass"], "reason": d["reason"], "measured_mm": d["measured_mm"],
                    "position": d["position"]} for d in ctl.journal.defect_rows()]
    failed = ctl.journal.failed if ctl.journal is not None else None
    if failed and not any(a["message"] == failed for a in alarms):  # the alarm row itself may be lost
        alarms.append({"message": failed, "kind": "fault", "layer": None, "pass": None, "position": None})
    return {"state": res.state, "layers_done": res.layers_done, "passes_done": res.passes_done,
            "complete_with_defects": res.state == "complete" and bool(defects), "defects": defects,
            "arc_starts": res.arc_starts, "alarms": alarms, "report": str(report) if report else None,
            "run_dir": str(ctl.run_dir) if ctl.run_dir else None,
            # link health over the run (docs/contract.md §5): late replies are counted, never a fault
            "links": [dataclasses.asdict(x) for x in ctl.snapshot().links]}


# -- cell run -------------------------------------------------------------------------------------


def _run(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.jobs import run_dir_for

    cfg = runargs.with_trace(load_cell(args.cell_config), args)
    job = read_job(args.job)
    sim_faults, scen = split_faults(args.fault)
    if (args.fault and not args.sim):
        raise InputError("--fault needs --sim (for `cell sim up`, give it --fault there)")
    runs = runargs.dir_arg(args.runs or cfg.cell.runs_dir, "--runs")
    if args.sim_log:
        runargs.dir_arg(args.sim_log, "--sim-log")
    # the whole job against the cell, before any simulator starts or device is touched
    check_job_for_cell(job, cfg, str(args.job))
    run_dir = run_dir_for(job, runs)
    if complete_in(run_dir, job) and not args.new:
        return _already_complete(args, run_dir)
    if args.new and (run_dir / "journal.sqlite").exists():
        run_dir = runargs.new_run_dir(run_dir)
    log_dir = Path(args.sim_log) if args.sim_log else run_dir / "sim"
    check_free_space(run_dir, job, args.max_step, cfg.cell.time_scale)  # before any device (exit 2)
    return _build(args, cfg, job, run_dir, sim_faults, scen, log_dir, runs)


def _already_complete(args: argparse.Namespace, run_dir: Path) -> int:
    """`cell run` of a job the runs directory holds complete: say so, build nothing, exit 0."""
    msg = (f"{args.job}: already complete in {run_dir} (nothing built); "
           "`cell run --new` builds it again in a new run directory")
    if args.json:
        # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
        from controller.cli.main import emit_json

        report = run_dir / "report.json"
        emit_json({"state": "complete", "already_complete": True, "layers_done": None, "passes_done": None,
                   "arc_starts": 0, "alarms": [], "defects": [],
                   "report": str(report) if report.exists() else None, "run_dir": str(run_dir),
                   "message": msg})
    else:
        out_line(msg)
    return 0


def _resume(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.jobs import stored_job
    from controller.api.runs import journal_head, latest_run_dir

    cfg = runargs.with_trace(load_cell(args.cell_config), args)
    runs = runargs.dir_arg(args.runs or cfg.cell.runs_dir, "--runs", must_exist=not args.run_dir)
    if args.sim_log:
        runargs.dir_arg(args.sim_log, "--sim-log")
    run_dir = runargs.dir_arg(args.run_dir, "RUN_DIR", must_exist=True) if args.run_dir else latest_run_dir(runs)
    jpath = run_dir / "journal.sqlite"
    if not jpath.exists() and not jpath.with_name(jpath.name + "-wal").exists():
        raise CellError(f"{run_dir}: no journal.sqlite here; nothing to resume")
    head = journal_head(jpath)  # refuses a damaged journal, untouched
    meta = head.job
    if head.mode.get("sim") and not args.sim:
        # the interrupted build ran on in-process simulators: so does its resume
        args.sim = True
    if meta is None:
        raise CellError(f"journal {jpath} holds no job, so it cannot be resumed (left untouched; "
                        f"`cell journal check {run_dir}` says what is readable)")
    job = stored_job(meta, jpath)
    check_job_for_cell(job, cfg, str(jpath))
    log_dir = Path(args.sim_log) if args.sim_log else run_dir / "sim"
    check_free_space(run_dir, job, args.max_step, cfg.cell.time_scale)  # before any device (exit 2)
    return _build(args, cfg, job, run_dir, "", [], log_dir, runs, resume=True)


def _build(args: argparse.Namespace, cfg: CellConfig, job: CellJob, run_dir: Path | None, faults: str,
           scen: list[tuple[str, int, float | None]], log_dir: Path, runs: Path, resume: bool = False) -> int:
    fed: FedScale | None = None
    note = None
    if args.sim:  # issue 29: the time scale the CNC link can feed (controller/motion/cnc5.py), said on stderr
        # lazy: the 5-axis post loads only for a simulated build
        from controller.api import feedable_time_scale

        cfg, note = feedable_time_scale(cfg, job)
    elif cfg.cell.platform == "cnc":
        # `cell sim up`: its clock lowered to what the host can feed, before any device, or refused
        # (docs/controller.md, "Simulated time the host can feed")
        from controller.harness import FedScale

        fed = FedScale.lower(cfg, job, args.max_step)
        cfg, note = fed.cfg, fed.note
    if note:
        err_line(note)
    say = err_line if args.json else out_line
    sim = load_sim(args.sim_config) if args.sim else None
    reset = resume or bool(getattr(args, "reset_errors", False))
    try:
        ctl = asyncio.run(_open_and_drive(cfg, job, run_dir, runs, sim, log_dir, faults, scen, say, resume,
                                          {"max_step_mm": args.max_step, "reset_errors": reset}, note))
    finally:
        if fed is not None:
            fed.restore()
    out = ctl.result_json
    if out and note:
        out["time_scale"] = cfg.cell.time_scale
        out["notes"] = [note]
    if args.json:
        # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
        from controller.cli.main import emit_json

        emit_json(out)
    else:
        print_summary(out, say)
    return exit_code(out)


EXIT_COMPLETE_WITH_DEFECTS = 3


def exit_code(out: dict[str, Any]) -> int:
    """0 complete, 3 complete with defects, 1 stopped (fault, E-stop, abort)."""
    stopped = guard.exit_code(out["state"])  # stopped by a signal: 130 / 143 / 129
    if stopped is not None:
        return stopped
    if out["state"] != "complete":
        return 1
    return EXIT_COMPLETE_WITH_DEFECTS if out.get("defects") else 0


async def _open_and_drive(cfg: CellConfig, job: CellJob, run_dir: Path | None, runs: Path, sim: SimConfig | None,
                          log_dir: Path, faults: str, scen: list[tuple[str, int, float | None]],
                          say: Callable[[str], None], resume: bool, options: dict[str, Any],
                          note: str | None = None) -> Any:
    """The cell opened (controller/harness/cell.py: the simulators in this process with `sim`),
    the build driven, the cell closed; the API object (its `result_json`)."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.types import BuildOptions
    from controller.harness import open_cell

    async with open_cell(cfg, sim=sim, runs_dir=runs, log_dir=log_dir if sim is not None else None,
                         faults=faults, connect=False) as ctl:
        ctl.options = BuildOptions(**{**ctl.options.__dict__, **options})
        await drive(ctl, job, run_dir, scen, say, resume, note)
    return ctl


async def drive(ctl: Any, job: CellJob, run_dir: Path | None, scen: list[tuple[str, int, float | None]],
                 say: Callable[[str], None], resume: bool, note: str | None = None) -> tuple[Any, Path | None]:
    resume_ticket = None
    if resume and run_dir is not None:
        # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
        from controller.api.runs import journal_head

        resume_ticket = journal_head(run_dir / "journal.sqlite").resume_ticket
    guard.attach(ctl, say)  # SIGINT / SIGTERM / SIGHUP: the fault path from here on
    await ctl.connect(resume_ticket=resume_ticket)
    try:
        # checked, hashed and journaled off the loop that cycles the devices (docs/testing.md)
        await asyncio.to_thread(ctl.open_job, job, run_dir)
        ctl.journal.event("mode", json.dumps({"sim": ctl.simulators is not None}))
        if note:   # the time scale the host can feed, in the record (docs/controller.md)
            ctl.journal.event("info", f"time scale: {note}")
        ctl.subscribe(Progress(say))
        prompt = PausePrompt(ctl, say)   # a pause says why and how to go on, and takes the answer here
        if resume:
            # `cell resume` is the operator's explicit reset: clear what the crash latched on the
            # power source (its watchdog) and flush what the robot still holds queued
            await ctl.arc.reset()
            ctl.journal.event("info", "cell resume: reconnected, reset, continuing from the journal")
            if ctl.devices.robot is not None:
                st = ctl.devices.robot.last_status
                ctl.journal.event("info", f"robot: last executed seq {st.last_exec} (ticket {st.last_exec_ticket}), "
                                          f"state {st.state}")
        tasks = []
        if scen and ctl.simulators is not None:
            tasks.append(asyncio.ensure_future(_scenario(ctl, ctl.simulators, scen)))
        say(f"building {ctl.bus.latest.job_name}: {ctl.bus.latest.layers_total} layers, "
            f"{ctl.bus.latest.passes_total} passes ({ctl.bus.latest.passes_done} already done); run dir {ctl.run_dir}")
        res = await ctl.start()
        prompt.close()
        for t in tasks:
            t.cancel()
        await ctl.disconnect()
        report = _report(ctl)
        ctl.result_json = _result_json(ctl, res, report)
        return res, report
    finally:
        guard.detach()   # the caller closes the cell (controller/harness/cell.py)


def _report(ctl: Any) -> Path | None:
    """The build record; none when the journal could not be written (the fault said where)."""
    if ctl.journal is not None and ctl.journal.failed:
        last: Path | None = ctl.last_report
        return last
    try:
        report: Path | None = ctl.last_report or ctl.write_report()
        return report
    except OSError:
        if ctl.journal is None or not ctl.journal.failed:
            raise
        return None


def print_summary(out: dict[str, Any], say: Callable[[str], None]) -> None:
    defects = out.get("defects") or []
    state = out["state"] + (f" with {len(defects)} defects" if defects and out["state"] == "complete" else "")
    say(f"state {state}: {out['layers_done']} layers, {out['passes_done']} passes done, "
        f"{out['arc_starts']} arc starts")
    for d in defects[:20]:
        pos = f" at {tuple(round(v, 2) for v in d['position'])}" if d["position"] else ""
        say(f"  defect: layer {d['layer']}, pass {d['pass']}{pos}: {d['reason']}")
    if len(defects) > 20:
        say(f"  ... and {len(defects) - 20} more defects (report.json)")
    for a in out["alarms"]:
        where = f" at layer {a['layer']}, pass {a['pass']} (job indices)" if a["layer"] is not None else ""
        pos = f", position {tuple(round(v, 2) for v in a['position'])}" if a["position"] else ""
        say(f"  alarm: {a['message']}{where}{pos}")
    _say_record(out.get("report"), say)
    say(f"report: {out['report']}")


def _say_record(report: str | None, say: Callable[[str], None]) -> None:
    """The record's cross-checks in two lines: arc times, travel speed, starvation."""
    try:
        rep = json.loads(Path(report).read_text(encoding="utf-8")) if report else None
    except (OSError, ValueError):
        return
    if not rep:
        return
    a, ts = rep.get("arc_time_figures") or {}, rep.get("travel_speed") or {}
    if a.get("plan_s"):
        say(f"arc time: plan {a['plan_s'] / 60:.1f} min, deposited {a['measured_s'] / 60:.1f} min at the measured "
            f"speed ({'agree' if a.get('agree') else 'DISAGREE'} within 2 %)")
    if ts.get("beads_measured"):
        flagged = len(ts.get("off_speed_beads") or [])
        say(f"travel speed: worst bead {100 * ts['worst_deviation']:+.1f} % from plan, {flagged} bead(s) outside "
            f"±{ts.get('tolerance_pct', 10):g} %, {ts.get('starved_beads', 0)} bead(s) with the motion queue run empty")


# -- cell demo ------------------------------------------------------------------------------------

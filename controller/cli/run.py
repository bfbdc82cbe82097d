"""`cell run JOB`, `cell resume`, `cell demo`: build a job on the cell (or its simulators).

- `cell run JOB [--sim] [--fault SPEC] [--json]`: without `--sim` the devices of cell.yaml
  (real ones, or `cell sim up`); with it, every simulator starts in this process.
- `cell resume [RUN_DIR] [--sim] [--json]`: after a crash or a fault, reconnect, reset, and
  continue the build of the latest (or the given) run directory from its journal.
- `cell demo [--json]`: simulators up, plan the demo part, probe and align the substrate,
  build it at the demo's time scale, write the report, print the summary.

Exit status: 0 when the build completed, 1 when it stopped (fault, E-stop, abort), 2 on bad
input or an unreachable device (one `error:` line).
"""
from __future__ import annotations

import argparse
import os
import asyncio
import json
import re
import sys
import time
from pathlib import Path
from typing import Any, Callable

from controller.config import CONFIG_DIR, CellConfig, load_cell, load_sim
from controller.jobfile import read_job
from planner.errors import CellError, InputError

DEMO_PART = CONFIG_DIR / "parts" / "square-hole.stl"
DEMO_WIDTH_MM = 7.0          # Inconel 718 bead; 39 layers of 0.77 mm for the 30 mm part
DEMO_TIME_SCALE = 120.0      # ~70 min of arc in ~35 s of motion; the 10k weld frames at 115200 baud take ~50 s
DEMO_MAX_STEP_MM = 6.0       # split only long demo segments (the planner's own points are 1.7 mm apart, median)
SIM_REPLY_TIMEOUT_MS = 250.0  # in-process simulators share the GIL with the controller


def sim_reply_timeout_ms() -> float:
    """Bus reply timeout with in-process simulators; CELL_SIM_REPLY_TIMEOUT_MS overrides it
    (a heavily loaded test machine, where the simulators and the UI share one interpreter)."""
    raw = os.environ.get("CELL_SIM_REPLY_TIMEOUT_MS")
    if raw is None:
        return SIM_REPLY_TIMEOUT_MS
    try:
        value = float(raw)
    except ValueError:
        raise InputError(f"CELL_SIM_REPLY_TIMEOUT_MS={raw!r} is not a number of milliseconds") from None
    if value <= 0:
        raise InputError(f"CELL_SIM_REPLY_TIMEOUT_MS={raw!r} must be positive")
    return value
SCENARIO_FAULTS = ("arc_loss", "wire_stick")  # `name@layer=N` is driven by the controller's sim harness


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="build a job on the cell (or on its simulators with --sim)")
    p.add_argument("job", metavar="JOB", help="job file (cell-job/1 JSON, from `cell plan`)")
    _common(p)
    p.add_argument("--fault", metavar="SPEC", default=None,
                   help="seeded fault spec for the simulators, e.g. 'seed=7,corrupt=0.01,arc_loss@layer=3' (--sim)")
    p.set_defaults(func=_run)
    r = sub.add_parser("resume", help="continue an interrupted build from its journal")
    r.add_argument("run_dir", metavar="RUN_DIR", nargs="?", default=None,
                   help="run directory (default: the latest under runs/)")
    _common(r)
    r.set_defaults(func=_resume)
    d = sub.add_parser("demo", help="the demo: simulators, plan, align, build, report")
    d.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    d.add_argument("--time-scale", type=float, default=DEMO_TIME_SCALE, help=argparse.SUPPRESS)
    d.add_argument("--layers", type=int, default=None, help=argparse.SUPPRESS)  # quick demo in tests
    d.add_argument("--runs", default=None, metavar="DIR", help="runs directory (default cell.yaml's runs_dir)")
    d.add_argument("--no-align", action="store_true", help="skip probing and aligning the substrate")
    d.set_defaults(func=_demo)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sim", action="store_true", help="start every simulator in this process")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.add_argument("--cell-config", default=None, metavar="FILE", help="cell config (default config/cell.yaml)")
    p.add_argument("--sim-config", default=None, metavar="FILE", help="simulator config with --sim")
    p.add_argument("--runs", default=None, metavar="DIR", help="runs directory (default cell.yaml's runs_dir)")
    p.add_argument("--max-step", type=float, default=2.0, metavar="MM",
                   help="split weld moves to at most this length (bounds the re-arc overlap; default 2)")
    p.add_argument("--sim-log", default=None, metavar="DIR",
                   help="with --sim: write the simulators' logs here (default RUN_DIR/sim)")


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
    from sims.faults import parse_fault_spec

    parse_fault_spec(",".join(keep))  # a bad key or value: ConfigError naming it
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
        sim = harness.sim("power_source")
        kw = {"duration_s": 0.5 if dur is None else dur} if name == "arc_loss" else {}
        harness.call(sim.inject, name, **kw)


class Progress:
    """Progress lines on stderr (stdout stays for --json)."""

    def __init__(self, out: Callable[[str], None]) -> None:
        from controller.events import ProgressPrinter

        self.t0 = time.monotonic()
        self.printer = ProgressPrinter(lambda line: out(f"[{time.monotonic() - self.t0:6.1f} s] {line}"))

    def __call__(self, snap: Any) -> None:
        self.printer(snap)


def _err(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def _out(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _result_json(ctl: Any, res: Any, report: Path | None) -> dict:
    alarms = []
    if ctl.journal is not None:
        for msg, st, la, pa, x, y, z in ctl.journal.query(
                "SELECT message, state, layer, pass, x, y, z FROM events WHERE kind='alarm' ORDER BY id"):
            alarms.append({"message": msg, "kind": st, "layer": la, "pass": pa,
                           "position": [x, y, z] if x is not None else None})
    return {"state": res.state, "layers_done": res.layers_done, "passes_done": res.passes_done,
            "arc_starts": res.arc_starts, "alarms": alarms, "report": str(report) if report else None,
            "run_dir": str(ctl.run_dir) if ctl.run_dir else None}


class SimSession:
    """The simulators in this process (with --sim) or nothing (devices of cell.yaml)."""

    def __init__(self, cfg: CellConfig, use_sim: bool, sim_config: str | None, log_dir: Path | None,
                 faults: str = "") -> None:
        self.harness = None
        self.cfg = cfg
        if use_sim:
            from controller.cell import SimHarness, with_urls

            self.harness = SimHarness(cfg, load_sim(sim_config), log_dir=log_dir, faults=faults)
            self.cfg = with_urls(cfg, self.harness.start())

    @property
    def reply_timeout_ms(self) -> float | None:
        return sim_reply_timeout_ms() if self.harness is not None else None

    def close(self) -> None:
        if self.harness is not None:
            self.harness.stop()


# -- cell run -------------------------------------------------------------------------------------


def _run(args: argparse.Namespace) -> int:
    from controller.build import run_dir_for

    cfg = load_cell(args.cell_config)
    job = read_job(args.job)
    sim_faults, scen = split_faults(args.fault)
    if (args.fault and not args.sim):
        raise InputError("--fault needs --sim (for `cell sim up`, give it --fault there)")
    runs = Path(args.runs or cfg.cell.runs_dir)
    run_dir = run_dir_for(job, runs)
    log_dir = Path(args.sim_log) if args.sim_log else run_dir / "sim"
    return _build(args, cfg, job, None, sim_faults, scen, log_dir, runs)


def _resume(args: argparse.Namespace) -> int:
    from controller.journal import Journal
    from controller.resume import latest_run_dir

    cfg = load_cell(args.cell_config)
    runs = Path(args.runs or cfg.cell.runs_dir)
    run_dir = Path(args.run_dir) if args.run_dir else latest_run_dir(runs)
    jpath = run_dir / "journal.sqlite"
    if not jpath.exists():
        raise CellError(f"{run_dir}: no journal.sqlite here; nothing to resume")
    j = Journal(jpath)
    meta = j.job()
    modes = j.query("SELECT message FROM events WHERE kind='mode' ORDER BY id DESC LIMIT 1")
    j.close()
    if modes and json.loads(modes[0][0]).get("sim") and not args.sim:
        # the interrupted build ran on in-process simulators: so does its resume
        args.sim = True
    if meta is None:
        raise CellError(f"{jpath}: the journal holds no job; start the build with `cell run JOB`")
    job = json.loads(meta["job_json"])
    log_dir = Path(args.sim_log) if args.sim_log else run_dir / "sim"
    return _build(args, cfg, job, run_dir, "", [], log_dir, runs, resume=True)


def _build(args: argparse.Namespace, cfg: CellConfig, job: dict, run_dir: Path | None, faults: str,
           scen: list, log_dir: Path, runs: Path, resume: bool = False) -> int:
    from controller.api import CellController
    from controller.build import BuildOptions

    session = SimSession(cfg, args.sim, args.sim_config, log_dir if args.sim else None, faults)
    say = _err if args.json else _out
    try:
        ctl = CellController(session.cfg, runs_dir=runs)
        o = ctl.options
        ctl.options = BuildOptions(**{**o.__dict__, "max_step_mm": args.max_step})
        res, report = asyncio.run(_drive(ctl, job, run_dir, session, scen, say, resume))
    finally:
        session.close()
    out = ctl.result_json
    if args.json:
        from controller.cli.main import emit_json

        emit_json(out)
    else:
        _print_summary(out, say)
    return 0 if res.state == "complete" else 1


async def _drive(ctl: Any, job: dict, run_dir: Path | None, session: SimSession, scen: list,
                 say: Callable[[str], None], resume: bool) -> tuple[Any, Path | None]:
    resume_ticket = None
    if resume and run_dir is not None:
        from controller.journal import Journal

        j = Journal(run_dir / "journal.sqlite")
        row = j.query("SELECT max(ticket) FROM progress")[0][0]
        j.close()
        resume_ticket = int(row) if row else None
    await ctl.connect(resume_ticket=resume_ticket, reply_timeout_ms=session.reply_timeout_ms)
    try:
        ctl.open_job(job, run_dir)
        ctl.journal.event("mode", json.dumps({"sim": session.harness is not None}))
        ctl.subscribe(Progress(say))
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
        if scen and session.harness is not None:
            tasks.append(asyncio.ensure_future(_scenario(ctl, session.harness, scen)))
        say(f"building {ctl.bus.latest.job_name}: {ctl.bus.latest.layers_total} layers, "
            f"{ctl.bus.latest.passes_total} passes ({ctl.bus.latest.passes_done} already done); run dir {ctl.run_dir}")
        res = await ctl.start()
        for t in tasks:
            t.cancel()
        await ctl.disconnect()
        report = ctl.write_report()
        ctl.result_json = _result_json(ctl, res, report)
        return res, report
    finally:
        await ctl.close()


def _print_summary(out: dict, say: Callable[[str], None]) -> None:
    say(f"state {out['state']}: {out['layers_done']} layers, {out['passes_done']} passes done, "
        f"{out['arc_starts']} arc starts")
    for a in out["alarms"]:
        where = f" at layer {a['layer']}, pass {a['pass']} (job indices)" if a["layer"] is not None else ""
        pos = f", position {tuple(round(v, 2) for v in a['position'])}" if a["position"] else ""
        say(f"  alarm: {a['message']}{where}{pos}")
    say(f"report: {out['report']}")


# -- cell demo ------------------------------------------------------------------------------------


def _demo(args: argparse.Namespace) -> int:
    from controller.api import CellController
    from controller.build import BuildOptions, run_dir_for
    from controller.cell import with_urls
    from controller.config import load_material
    from planner.job import job_to_dict
    from planner.plan import PlanOptions, plan_part

    say = _err if args.json else _out
    t0 = time.monotonic()
    cfg = load_cell()
    cfg = with_urls(cfg, {}, time_scale=args.time_scale)
    mat = load_material(cfg.cell.material)
    say(f"planning {DEMO_PART.name}: {DEMO_WIDTH_MM} mm beads of {mat.name}, perimeters until they meet (Fang 2019)")
    job = job_to_dict(plan_part(str(DEMO_PART), PlanOptions(width_mm=DEMO_WIDTH_MM, perimeters="all"), mat))
    job = json.loads(json.dumps(job))
    if args.layers:
        job["layers"] = job["layers"][: args.layers]
    s = job["summary"]
    say(f"  {len(job['layers'])} layers, {sum(len(la['passes']) for la in job['layers'])} beads, "
        f"{s.get('deposit_length_mm', 0) / 1000:.1f} m of bead, about {s.get('est_time_s', 0) / 60:.0f} min of arc")
    runs = Path(args.runs or cfg.cell.runs_dir)
    run_dir = run_dir_for(job, runs)
    if (run_dir / "journal.sqlite").exists():
        # a fresh demo each time: keep the old one beside it
        old = run_dir.with_name(run_dir.name + time.strftime("-%Y%m%d-%H%M%S"))
        run_dir.rename(old)
    session = SimSession(cfg, True, None, run_dir / "sim")
    say(f"simulators up at time scale {cfg.cell.time_scale:g} (process time {cfg.cell.time_scale:g}x wall time)")
    try:
        ctl = CellController(session.cfg, runs_dir=runs)
        ctl.options = BuildOptions(**{**ctl.options.__dict__, "max_step_mm": DEMO_MAX_STEP_MM})
        res, report, align = asyncio.run(_demo_drive(ctl, job, session, say, not args.no_align))
    finally:
        session.close()
    out = ctl.result_json
    out["alignment"] = align
    out["wall_time_s"] = round(time.monotonic() - t0, 1)
    if args.json:
        from controller.cli.main import emit_json

        emit_json(out)
    else:
        _print_summary(out, say)
        say(f"run directory: {out['run_dir']} (journal.sqlite, report.json, layers.png, process.png, "
            f"temperature.png, defects.png); {out['wall_time_s']} s wall")
    return 0 if res.state == "complete" else 1


async def _demo_drive(ctl: Any, job: dict, session: SimSession, say: Callable[[str], None],
                      do_align: bool) -> tuple[Any, Path | None, dict | None]:
    align = None
    if do_align:
        align = await _align(session, say)
    res, report = await _drive(ctl, job, None, session, [], say, False)
    if align is not None:
        rep = json.loads(report.read_text(encoding="utf-8"))
        rep["alignment"] = align
        report.write_text(json.dumps(rep, indent=2) + "\n", encoding="utf-8")
    return res, report, align


async def _align(session: SimSession, say: Callable[[str], None]) -> dict | None:
    """Probe and align the substrate over the CNC link, when the alignment routine is installed."""
    try:
        from controller.align.routine import cad_mesh, plan_for_mesh, run_on_url
    except ImportError:
        say("alignment: routine not installed, skipped")
        return None
    cfg = session.cfg
    sim_cfg = session.harness.sim_cfg if session.harness is not None else load_sim()
    say("probing and aligning the substrate on the CNC (touch probe, G38.2)...")
    try:
        plan = plan_for_mesh(cad_mesh(sim_cfg.cnc.workpiece))
        res = await asyncio.wait_for(run_on_url(cfg.devices.cnc.url, cfg, plan), 60.0)
    except (CellError, asyncio.TimeoutError) as exc:
        say(f"alignment failed: {exc or 'timed out'}; building without it")
        return {"error": str(exc) or "timed out"}
    out = {"level_a_deg": round(res.level_a_deg, 5), "level_b_deg": round(res.level_b_deg, 5),
           "face_angle_deg": round(res.face_angle_deg, 5), "transform": res.transform.tolist()}
    say(f"  leveling A {out['level_a_deg']}°, B {out['level_b_deg']}°, face angle {out['face_angle_deg']}°")
    return out

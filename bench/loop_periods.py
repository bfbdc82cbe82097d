"""Device cycle periods of the demo part built from the command line and from the TUI (issue 38 item 2).

Plans the demo part (config/parts/square-hole.stl, the demo's options), cuts it to `--layers`,
then builds it twice with the simulators in the building process (`--sim`), each in a fresh
process: `cell run JOB --sim` and the TUI (`CellApp` headless, Textual's own loop on the main
thread, the controller on its thread). The figures are the power source's and the cell I/O's
link statistics the journal keeps at the build's end (drivers/cyclic.py): cycles, late replies,
the period's p99 and maximum, the longest period the controller is to blame for and the OS's
share of the longest (docs/testing.md, "A loop that never blocks").

    .venv/bin/python -m bench.loop_periods --layers 6
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
CYCLIC = ("power_source", "cellio")


def plan_demo(out: Path, layers: int) -> Path:
    """The demo part's job (as `cell demo` plans it), its first `layers` layers."""
    # lazy: the planner loads only in the process that plans
    from controller.cli.demo import DEMO_PART, DEMO_WIDTH_MM
    from core.config import load_cell, load_material
    from planner.job import job_to_dict
    from planner.plan import PlanOptions, plan_part

    mat = load_material(load_cell().cell.material)
    plan = plan_part(str(DEMO_PART), PlanOptions(width_mm=DEMO_WIDTH_MM, perimeters="all"), mat)
    obj = json.loads(json.dumps(job_to_dict(plan)))
    obj["layers"] = obj["layers"][:layers]
    path = out / "demo-part.json"
    path.write_text(json.dumps(obj))
    return path


def links_of(runs: Path) -> list[dict[str, Any]]:
    """The cyclic links of the last `links` row of every journal under `runs`."""
    out: list[dict[str, Any]] = []
    for j in sorted(runs.rglob("journal.sqlite")):
        con = sqlite3.connect(f"file:{j}?mode=ro", uri=True)
        rows = con.execute("SELECT message FROM events WHERE kind='links' ORDER BY id").fetchall()
        con.close()
        if rows:
            out += [x for x in json.loads(rows[-1][0]) if x["device"] in CYCLIC]
    return out


def cli_build(job: Path, runs: Path, scale: float, max_step: float,
              sim_up: Path | None) -> tuple[float, list[dict[str, Any]]]:
    cfg = sim_up or _cell_yaml(runs.parent, scale)
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "controller.cli.main", "run", str(job), "--json",
                           *(() if sim_up else ("--sim",)),
                           "--cell-config", str(cfg), "--runs", str(runs), "--max-step", str(max_step),
                           "--wire-lot", "BENCH"], capture_output=True, text=True, cwd=ROOT)
    wall = time.monotonic() - t0
    if proc.returncode not in (0, 3):
        raise SystemExit(f"cell run exited {proc.returncode}: {proc.stderr.strip()[-400:]}")
    return wall, links_of(runs)


def _cell_yaml(where: Path, scale: float) -> Path:
    """cell.yaml with the time scale and a wire lot (so the TUI's start dialog is not needed)."""
    # lazy: only the processes that write a cell.yaml load the YAML writer
    import yaml

    obj = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    obj["cell"]["time_scale"] = scale
    obj.setdefault("records", {})["wire_lot"] = "BENCH"
    path = where / "cell.yaml"
    path.write_text(yaml.safe_dump(obj))
    for name in ("materials", "power_source.dbc"):   # the files cell.yaml names beside it
        if not (where / name).exists():
            os.symlink(ROOT / "config" / name, where / name)
    return path


def tui_build(job: Path, runs: Path, scale: float, max_step: float,
              sim_up: Path | None, tab: str = "build") -> tuple[float, list[dict[str, Any]]]:
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "bench.loop_periods", "--tui-child", str(job), str(runs),
                           str(scale), str(sim_up or ""), tab], capture_output=True, text=True, cwd=ROOT)
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise SystemExit(f"TUI build failed: {proc.stdout.strip()[-400:]} {proc.stderr.strip()[-800:]}")
    for line in proc.stdout.strip().splitlines()[-2:]:
        print(f"tui build: {line}", flush=True)
    return wall, links_of(runs)


def thread_cpu() -> dict[str, float]:
    """CPU seconds of this process's threads by name (the screen's, the controller's, ...)."""
    # lazy: only the TUI child lists its threads
    import threading

    out: dict[str, float] = {}
    for t in threading.enumerate():
        try:
            with open(f"/proc/self/task/{t.native_id}/schedstat") as f:
                out[t.name] = out.get(t.name, 0.0) + int(f.read().split()[0]) / 1e9
        except (OSError, ValueError):
            pass
    return out


async def _tui(job: Path, runs: Path, scale: float, sim_up: str, tab: str) -> str:
    # lazy: Textual loads only in the TUI child
    from controller.tui.app import CellApp
    from controller.tui.session import CellSession
    from core.config import load_cell

    cfg = load_cell(Path(sim_up) if sim_up else _cell_yaml(runs.parent, scale))
    session = CellSession(cfg, sim=not sim_up, runs_dir=runs)
    app = CellApp(session)
    async with app.run_test(size=(120, 36)):
        async def until(cond: Any, timeout: float, what: str) -> None:
            t0 = time.monotonic()
            while not cond():
                if time.monotonic() - t0 > timeout:
                    raise SystemExit(f"timed out waiting for {what}: {app.last_message!r}")
                # a plain sleep: the pilot's pause waits for every widget's queue (a walk of the
                # whole tree, five times a second), work `cell tui` itself never does
                await asyncio.sleep(0.2)

        await until(lambda: app.view.snap.state == "idle", 60, "the simulators to connect")
        session.choose_file(job).result(60)
        await until(lambda: app.view.snap.state == "ready", 60, "the job to open")
        app.action_tab(tab)   # what the operator watches during the build (the Build screen by default)
        cpu0, t0 = thread_cpu(), time.monotonic()
        session.command("start").result(30)
        await until(lambda: app.view.snap.state in ("complete", "fault", "estop", "aborted"), 3600, "the build")
        cpu1, wall = thread_cpu(), time.monotonic() - t0
        print("thread CPU during the build (s per s): " + ", ".join(
            f"{k} {(v - cpu0.get(k, 0.0)) / wall:.3f}" for k, v in sorted(cpu1.items(), key=lambda kv: -kv[1])))
        snap = app.view.snap
        state = f"{snap.state}, {snap.passes_done} passes" + "".join(f"; {a.message}" for a in snap.alarms)
        report = Path(app.view.snap.run_dir or ".") / "report.json"
        await until(report.exists, 300, "the record")
    session.close()
    return state


def _row(name: str, wall: float, links: list[dict[str, Any]]) -> str:
    parts = [f"{name:4s} {wall:6.1f} s"]
    for x in links:
        parts.append(f"{x['device']}: {x['frames_tx']} cycles, {x['late']} late, p99 {x.get('p99_period_ms')} ms, "
                     f"max {x.get('max_period_ms')} ms (controller's {x.get('max_own_period_ms')}, "
                     f"OS {x.get('os_delay_ms')}, devices {x.get('device_delay_ms')})")
    return " | ".join(parts)


def main(argv: list[str] | None = None) -> int:
    args_in = sys.argv[1:] if argv is None else argv
    if args_in and args_in[0] == "--tui-child":
        job, runs, scale = Path(args_in[1]), Path(args_in[2]), float(args_in[3])
        print(asyncio.run(_tui(job, runs, scale, args_in[4], args_in[5])))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=6, help="layers of the demo part (39 in all)")
    ap.add_argument("--time-scale", type=float, default=60.0)
    ap.add_argument("--max-step", type=float, default=2.0, help="weld move length, mm (both builds: the TUI's is 2)")
    ap.add_argument("--only", choices=("cli", "tui"), default=None)
    ap.add_argument("--tab", choices=("job", "align", "build", "log", "devices"), default="build",
                    help="the TUI's screen shown during the build")
    ap.add_argument("--sims", choices=("inproc", "process"), default="inproc",
                    help="the simulators in the building process (--sim) or in `cell sim up` beside it")
    a = ap.parse_args(args_in)
    with tempfile.TemporaryDirectory(prefix="loop-periods-") as tmp:
        t = Path(tmp)
        job = plan_demo(t, a.layers)
        out = {}
        for name in ("cli", "tui"):
            if a.only and a.only != name:
                continue
            d = t / name
            d.mkdir()
            sims = None
            if a.sims == "process":
                # lazy: only this topology starts `cell sim up`
                from controller.harness.cell import start_simulators
                from core.config import load_cell

                _cfg, sims = asyncio.run(start_simulators(load_cell(_cell_yaml(d, a.time_scale)), True, process=True,
                                                          log_dir=d / "sim"))
            try:
                sim_up = d / "sim" / "cell.yaml" if sims else None
                wall, links = (tui_build(job, d / "runs", a.time_scale, a.max_step, sim_up, a.tab) if name == "tui"
                               else cli_build(job, d / "runs", a.time_scale, a.max_step, sim_up))
            finally:
                if sims is not None:
                    sims.stop()
            out[name] = {"wall_s": round(wall, 1), "links": links}
            print(_row(name, wall, links), flush=True)
        print(json.dumps({"layers": a.layers, "time_scale": a.time_scale, "sims": a.sims, "tab": a.tab, **out}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

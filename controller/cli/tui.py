"""`cell tui [--sim]`: the operator's terminal UI (controller/tui/)."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from controller.cli import guard
from controller.cli.parsing import Subcommands

if TYPE_CHECKING:
    from controller.tui.session import CellSession
    from core.config import CellConfig


def register(sub: Subcommands) -> None:
    p = sub.add_parser("tui", help="the operator's terminal UI (Job, Align, Build, Log, Devices)")
    p.add_argument("--sim", action="store_true",
                   help="start the simulators (`cell sim up` in a process of its own) and connect to them")
    p.add_argument("--config", type=Path, default=None, help="cell.yaml (default: config/cell.yaml)")
    p.add_argument("--sim-config", type=Path, default=None, help="sim.yaml for --sim (default: config/sim.yaml)")
    p.add_argument("--fault", default="", metavar="SPEC", help="seeded fault spec for the simulators (--sim)")
    p.add_argument("--runs", type=Path, default=None, help="runs directory (default: cell.yaml's runs_dir)")
    p.set_defaults(func=_tui)


def _tui(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from core.config import load_cell, load_sim
    from controller.tui.session import CellSession

    cfg = load_cell(args.config)
    sim_cfg = load_sim(args.sim_config) if args.sim else None
    sims = None
    tmp = None
    if args.sim:
        # lazy: loaded only with --sim
        import asyncio
        import tempfile
        from controller.harness import start_simulators

        # the simulators in a process of their own, as `cell demo` runs them: in this one they
        # would share the interpreter lock with the controller's device cycles and the screen
        # (docs/tui.md: the cycle period's p99 35.7 ms in one process, 19.6 ms beside it)
        tmp = tempfile.TemporaryDirectory(prefix="cell-tui-sim-")
        cfg, sims = asyncio.run(start_simulators(cfg, True, process=True, log_dir=Path(tmp.name),
                                                 faults=args.fault, sim_config=args.sim_config))
    session = CellSession(cfg, sim_cfg=sim_cfg, runs_dir=args.runs, sims_beside=args.sim)
    try:
        return _serve(session, cfg, args)
    finally:
        if sims is not None:
            sims.stop()
        if tmp is not None:
            tmp.cleanup()


def _serve(session: "CellSession", cfg: "CellConfig", args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.tui.app import CellApp

    with guard.guarded(cfg, args.config) as stops:
        app = CellApp(session)

        def on_stop(reason: str) -> None:
            # the controller runs on the session's loop (a thread): the fault path there at once
            # (weld start dropped, motion held, journaled), then the UI ends; close() disconnects
            ctl = session.ctl
            if ctl is not None:
                session.loop.call_soon_threadsafe(ctl.stop_now, reason)
            app.exit(stops.exit_code() or 1)

        stops.forward(on_stop)
        try:
            code = int(app.run() or 0)
        finally:
            session.close()
        return stops.exit_code() or code

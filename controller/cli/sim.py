"""`cell sim up`: serve every simulator on the URLs of cell.yaml."""
from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path

from core.config import load_cell, load_material, load_sim
from sims.clock import SimClock
from sims.loop import precise_loop
from sims.up import SimContext, run_forever
from sims.world import World


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="device simulators")
    s = p.add_subparsers(dest="sim_command", metavar="SUBCOMMAND")
    s.required = True
    up = s.add_parser("up", help="serve every simulator on the URLs of cell.yaml until Ctrl-C")
    up.add_argument("--config", default=None, help="simulator config (default config/sim.yaml)")
    up.add_argument("--cell-config", default=None, help="cell config (default config/cell.yaml)")
    up.add_argument("--log", default=None, metavar="DIR", help="write execution and deposit logs here")
    up.add_argument("--pty", action="store_true", help="serial devices on ptys instead of loopback TCP")
    up.add_argument("--fault", default=None, metavar="SPEC", help="seeded fault spec (overrides sim.yaml)")
    up.set_defaults(func=_up)


def _up(args: argparse.Namespace) -> int:
    cell = load_cell(args.cell_config)
    sim = load_sim(args.config)
    mat = load_material(cell.cell.material)
    log_dir = Path(args.log) if args.log else None
    ctx = SimContext(
        cell=cell, sim=sim, world=World(log_dir, arc_efficiency=mat.arc_efficiency),
        clock=SimClock(cell.cell.time_scale), log_dir=log_dir, pty=args.pty,
        faults=args.fault if args.fault is not None else sim.faults,
    )

    def ready(served: list) -> None:
        for s in served:
            sys.stdout.write(json.dumps(s.describe()) + "\n")
        sys.stdout.flush()

    try:
        with asyncio.Runner(loop_factory=precise_loop) as runner:   # timers on time (sims/loop.py)
            runner.run(run_forever(ctx, ready))
    except KeyboardInterrupt:
        pass
    return 0

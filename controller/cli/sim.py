"""`cell sim up`: serve every simulator on the URLs of cell.yaml."""
from __future__ import annotations

import argparse
from pathlib import Path

from controller.cli.parsing import Subcommands
from controller.harness import serve_until_interrupted
from core.config import load_cell, load_sim


def register(sub: Subcommands) -> None:
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
    serve_until_interrupted(cell, sim, Path(args.log) if args.log else None, pty=args.pty,
                            faults=args.fault if args.fault is not None else sim.faults)
    return 0

"""Argument checks of `cell run` / `cell resume`, done before any device is touched (issue 14)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from core.errors import InputError

if TYPE_CHECKING:  # annotations only: the argument checks load before the job and the config do
    from core.config import CellConfig

MIN_STEP_MM = 0.1      # weld-move subdivision floor: 1 m of bead is at most 10 000 moves
MAX_STEP_MM = 1000.0


def max_step(text: str) -> float:
    """argparse type of --max-step: a finite length in [MIN_STEP_MM, MAX_STEP_MM] mm."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of mm") from None
    if not math.isfinite(v) or not MIN_STEP_MM <= v <= MAX_STEP_MM:
        raise argparse.ArgumentTypeError(f"{text} must lie in [{MIN_STEP_MM:g}, {MAX_STEP_MM:g}] mm")
    return v


def dir_arg(path: str | Path, what: str, *, must_exist: bool = False) -> Path:
    """A directory argument: a file there, or (with must_exist) nothing there, is an InputError."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{what} {p}: is a file, not a directory; give a directory")
    if must_exist and not p.is_dir():
        raise InputError(f"{what} {p}: no such directory; check the path")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{what} {p}: {parent} is a file, not a directory; give a directory")
            break
    return p


def new_run_dir(run_dir: Path) -> Path:
    """The first `<run_dir>-N` (N = 2, 3, ...) that does not exist yet: `cell run --new`."""
    n = 2
    while True:
        cand = run_dir.with_name(f"{run_dir.name}-{n}")
        if not cand.exists():
            return cand
        n += 1


def add_trace_args(p: argparse.ArgumentParser) -> None:
    """--wire-lot, --gas, --operator: the build's traceability (docs/records.md)."""
    p.add_argument("--wire-lot", default=None, metavar="LOT",
                   help="the wire lot this build is made from (default cell.yaml's records.wire_lot)")
    p.add_argument("--gas", default=None, metavar="GAS", help="the shielding gas (and its lot) (default records.gas)")
    p.add_argument("--operator", default=None, metavar="NAME",
                   help="who runs the build (default records.operator, then $CELL_OPERATOR)")


def with_trace(cfg: CellConfig, args: argparse.Namespace) -> CellConfig:
    """cell.yaml with the command's --wire-lot / --gas / --operator in its `records:` section, the
    build refused when cell.yaml requires a lot and none is given (before any device: exit 2)."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.api.runs import require_lot

    given = {k: v.strip() for k in ("wire_lot", "gas", "operator")
             if isinstance(v := getattr(args, k, None), str) and v.strip()}
    if given:
        cfg = cfg.model_copy(update={"records": cfg.records.model_copy(update=given)})
    require_lot(cfg)
    return cfg

"""`cell process inverse|forward|fit|stickout-fit`: the welding-parameter model (Ribeiro 1997) and the wire melting rate (Lesnewich 1958) on the command line.

CSV reading lives here, at the edge (planner/ stays pure): `read_csv_columns` is shared with
`cell bead fit`.
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from controller.cli.parsing import Subcommands
from core.errors import InputError

if TYPE_CHECKING:  # the config loader is imported when a command needs it (start-up time)
    from core.material import Material

FIT_COLUMNS = ("current_a", "speed_mm_min", "width_mm", "height_mm")
STICKOUT_COLUMNS = ("stick_out_mm", "wfs_m_min", "current_a")


# --- CSV input -------------------------------------------------------------------------------


def read_csv_columns(path: str | Path, columns: Sequence[str], *, positive: bool = False) -> dict[str, np.ndarray]:
    """Read the named numeric columns of a CSV file with a header line.

    Blank lines and lines starting with ``#`` are skipped; other columns are ignored. Every
    problem is an :class:`InputError` naming the file, the line and the column.
    """
    p = Path(path)
    text = _read_text(p)
    header: list[str] | None = None
    index: dict[str, int] = {}
    data: dict[str, list[float]] = {c: [] for c in columns}
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        row = _csv_row(p, lineno, line)
        if header is None:
            header = row
            index = _header_index(p, lineno, header, columns)
            continue
        if len(row) != len(header):
            raise InputError(f"{p}: line {lineno}: {len(row)} fields, but the header has {len(header)}")
        for c in columns:
            data[c].append(_cell_value(p, lineno, c, row[index[c]], positive))
    if header is None:
        raise InputError(f"{p}: empty file; expected a header line with columns {', '.join(columns)}")
    if not data[columns[0]]:
        raise InputError(f"{p}: no data rows after the header")
    return {c: np.asarray(v, dtype=np.float64) for c, v in data.items()}


def _read_text(p: Path) -> str:
    try:
        return p.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{p}: not a text (UTF-8) CSV file") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc}); check the path") from None


def _csv_row(p: Path, lineno: int, line: str) -> list[str]:
    """The stripped fields of one CSV line."""
    try:
        row = next(csv.reader([line]))
    except csv.Error as exc:
        raise InputError(f"{p}: line {lineno}: malformed CSV ({exc})") from None
    return [f.strip() for f in row]


def _header_index(p: Path, lineno: int, header: list[str], columns: Sequence[str]) -> dict[str, int]:
    """Column name → field index, for the wanted columns; each must appear exactly once."""
    seen: set[str] = set()
    for name in header:
        if name in seen and name in columns:
            raise InputError(f"{p}: line {lineno}: column '{name}' appears twice in the header")
        seen.add(name)
    index: dict[str, int] = {}
    for c in columns:
        if c not in header:
            hint = ""
            if all(_is_number(f) for f in header if f):
                hint = "; the first line must be a header naming the columns"
            raise InputError(
                f"{p}: line {lineno}: missing column '{c}' (header has: {', '.join(header) or 'nothing'}; "
                f"expected columns: {', '.join(columns)}){hint}"
            )
        index[c] = header.index(c)
    return index


def _cell_value(p: Path, lineno: int, c: str, raw: str, positive: bool) -> float:
    """One field as a finite number (and > 0 when `positive`)."""
    try:
        v = float(raw)
    except ValueError:
        raise InputError(f"{p}: line {lineno}, column '{c}': {raw!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(f"{p}: line {lineno}, column '{c}': {raw!r} is not a finite number")
    if positive and v <= 0.0:
        raise InputError(f"{p}: line {lineno}, column '{c}': {raw} must be positive")
    return v


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


# --- helpers ---------------------------------------------------------------------------------


def _material(name: str | None) -> Material:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from core.config import load_cell, load_material

    return load_material(name if name else load_cell().cell.material)


def _table(rows: Sequence[tuple[str, str]]) -> None:
    wid = max(len(k) for k, _ in rows)
    for k, v in rows:
        sys.stdout.write(f"{k:<{wid}}  {v}\n")
    sys.stdout.flush()


# --- commands --------------------------------------------------------------------------------


def register(sub: Subcommands) -> None:
    p = sub.add_parser("process", help="welding-parameter model (Ribeiro 1997)", description=__doc__.splitlines()[0])
    s = p.add_subparsers(dest="process_command", metavar="SUBCOMMAND")
    s.required = True

    inv = s.add_parser("inverse", help="current, travel speed and wire feed for a bead width (and height)")
    inv.add_argument("--width", type=float, required=True, metavar="W", help="bead width, mm")
    inv.add_argument("--height", type=float, default=None, metavar="H", help="bead height, mm (default: material ratio × width)")
    inv.add_argument("--material", default=None, metavar="M", help="material name or YAML file (default: cell.yaml's cell.material)")
    inv.add_argument("--allow-outside", action="store_true", help="return a point outside [Imin, Imax] / [WFSmin, WFSmax] instead of an error")
    inv.add_argument("--json", action="store_true", help="print one JSON object")
    inv.set_defaults(func=_inverse)

    fwd = s.add_parser("forward", help="bead width and height for a current and travel speed")
    fwd.add_argument("--current", type=float, required=True, metavar="I", help="welding current, A")
    fwd.add_argument("--speed", type=float, required=True, metavar="S", help="travel speed, mm/min")
    fwd.add_argument("--material", default=None, metavar="M", help="material name or YAML file (default: cell.yaml's cell.material)")
    fwd.add_argument("--json", action="store_true", help="print one JSON object")
    fwd.set_defaults(func=_forward)

    fit = s.add_parser("fit", help="refit K1-K6 from bead measurements (least squares on logarithms)")
    fit.add_argument("csv", metavar="CSV", help="columns current_a, speed_mm_min, width_mm, height_mm (header line required)")
    fit.add_argument("--json", action="store_true", help="print one JSON object")
    fit.set_defaults(func=_fit)

    so = s.add_parser("stickout-fit", help="refit the melting rate WFS = α·I + β·L·I² from a stick-out sweep")
    so.add_argument("csv", metavar="CSV", help="columns stick_out_mm, wfs_m_min, current_a (header line required)")
    so.add_argument("--json", action="store_true", help="print one JSON object")
    so.set_defaults(func=_stickout_fit)


def _inverse(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from planner.process import inverse

    mat = _material(args.material)
    pt = inverse(mat, args.width, args.height, allow_outside=args.allow_outside)
    if args.json:
        emit_json({**pt.to_dict(), "material": mat.name})
        return 0
    r = mat.ribeiro
    env = "inside" if pt.inside_envelope else "OUTSIDE (allowed by --allow-outside)"
    _table([
        ("material", mat.name),
        ("width", f"{pt.width_mm:.3f} mm"),
        ("height", f"{pt.height_mm:.3f} mm" + ("  (ratio × width)" if args.height is None else "")),
        ("current", f"{pt.current_a:.1f} A"),
        ("travel speed", f"{pt.speed_mm_min:.1f} mm/min"),
        ("wire feed", f"{pt.wfs_m_min:.2f} m/min"),
        ("envelope", f"{env}: {r.i_min_a:g}-{r.i_max_a:g} A, {r.wfs_min_m_min:g}-{r.wfs_max_m_min:g} m/min"),
    ])
    return 0


def _forward(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from planner.process import forward

    mat = _material(args.material)
    w, h = forward(mat, args.current, args.speed)
    if args.json:
        emit_json({"width_mm": w, "height_mm": h, "current_a": args.current, "speed_mm_min": args.speed, "material": mat.name})
        return 0
    _table([
        ("material", mat.name),
        ("current", f"{args.current:g} A"),
        ("travel speed", f"{args.speed:g} mm/min"),
        ("width", f"{w:.3f} mm"),
        ("height", f"{h:.3f} mm"),
    ])
    return 0


def _fit(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from planner.process_fit import fit_coefficients

    cols = read_csv_columns(args.csv, FIT_COLUMNS, positive=True)
    try:
        res = fit_coefficients(*(cols[c] for c in FIT_COLUMNS))
    except InputError as exc:
        raise InputError(f"{args.csv}: {exc}") from None
    if args.json:
        emit_json(res.to_dict())
        return 0
    _table([
        ("points", str(res.n_points)),
        ("width", f"w = {res.k1:.6g} · I^{res.k2:.6g} · S^{res.k3:.6g}   R² {res.r2_width:.4f} (ln), {res.r2_width_mm:.4f} (mm)"),
        ("height", f"h = {res.k4:.6g} · I^{res.k5:.6g} · S^{res.k6:.6g}   R² {res.r2_height:.4f} (ln), {res.r2_height_mm:.4f} (mm)"),
    ])
    sys.stdout.write(
        "\nfor the material file (ribeiro:):\n"
        f"  k1: {res.k1:.6g}\n  k2: {res.k2:.6g}\n  k3: {res.k3:.6g}\n"
        f"  k4: {res.k4:.6g}\n  k5: {res.k5:.6g}\n  k6: {res.k6:.6g}\n"
    )
    return 0


def _stickout_fit(args: argparse.Namespace) -> int:
    """α, β of the melting rate from a stick-out sweep (core/melting.py, docs/process-physics.md)."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from core.melting import fit_sweep

    cols = read_csv_columns(args.csv, STICKOUT_COLUMNS, positive=True)
    try:
        res = fit_sweep(*(cols[c] for c in STICKOUT_COLUMNS))
    except InputError as exc:
        raise InputError(f"{args.csv}: {exc}") from None
    if args.json:
        emit_json(res.to_dict())
        return 0
    _table([
        ("points", str(res.n)),
        ("melting rate", f"WFS = {res.alpha:.6g} · I + {res.beta:.6g} · L · I²   (m/min, A, mm)"),
        ("fit", f"R² {res.r2:.4f}, RMS {res.rms:.4f} m/min, stick-out read back RMS {res.rms_stick_out_mm:.3f} mm"),
    ])
    sys.stdout.write(f"\nfor the material file (melting:):\n  alpha: {res.alpha:.6g}\n  beta: {res.beta:.6g}\n")
    return 0

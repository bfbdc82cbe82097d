"""`cell bead critical-distance|fit`: bead profiles and the tangent overlapping model (Ding 2015)."""
from __future__ import annotations

import argparse
import sys
from typing import Any
from controller.cli.parsing import Subcommands

PROFILE_COLUMNS = ("x_mm", "y_mm")


def register(sub: Subcommands) -> None:
    p = sub.add_parser("bead", help="bead profiles and overlap (Ding 2015)", description=__doc__)
    s = p.add_subparsers(dest="bead_command", metavar="SUBCOMMAND")
    s.required = True

    cd = s.add_parser("critical-distance", help="critical centre distance d*/w of the tangent overlapping model")
    cd.add_argument("--model", default="parabola", choices=("parabola", "cosine", "arc"), help="bead profile (default parabola)")
    cd.add_argument("--aspect", type=float, default=None, metavar="H/W", help="height/width, arc profile only (default: mean of Ding 2015 Table 2)")
    cd.add_argument("--width", type=float, default=None, metavar="W", help="also give the step-over in mm for this bead width")
    cd.add_argument("--json", action="store_true", help="print one JSON object")
    cd.set_defaults(func=_critical)

    fit = s.add_parser("fit", help="fit parabola, cosine and arc to a measured bead profile")
    fit.add_argument("csv", metavar="CSV", help="columns x_mm, y_mm (header line required); y above the substrate")
    fit.add_argument("--min-height", type=float, default=None, metavar="MM",
                     help="ignore points at or below this height (default: 5 %% of the peak); the fit uses the contiguous points above it around the peak")
    fit.add_argument("--json", action="store_true", help="print one JSON object")
    fit.set_defaults(func=_fit)


def _critical(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from planner.bead import DING_ARC_ASPECT, critical_ratio, flat_top_ratio
    from core.errors import InputError

    if args.aspect is not None and args.model != "arc":
        raise InputError("--aspect applies to the arc profile only (the parabola's and cosine's d*/w do not depend on it)")
    if args.width is not None and not (args.width > 0 and args.width < float("inf")):
        raise InputError(f"--width must be a positive number of mm (got {args.width:g})")
    ratio = critical_ratio(args.model, args.aspect)
    flat = flat_top_ratio(args.model, args.aspect)
    out: dict[str, Any] = {"ratio": ratio, "model": args.model, "overlap": "tangent", "flat_top_ratio": flat}
    if args.model == "arc":
        out["aspect"] = DING_ARC_ASPECT if args.aspect is None else args.aspect
    if args.width is not None:
        out["width_mm"] = args.width
        out["step_over_mm"] = ratio * args.width
    if args.json:
        emit_json(out)
        return 0
    rows = [
        ("profile", args.model + (f" (h/w {out['aspect']:.3f})" if args.model == "arc" else "")),
        ("d*/w (tangent)", f"{ratio:.4f}"),
        ("d/w (flat top)", f"{flat:.4f}"),
    ]
    if args.width is not None:
        rows.append(("step-over", f"{ratio * args.width:.3f} mm for a {args.width:g} mm bead"))
    wid = max(len(k) for k, _ in rows)
    for k, v in rows:
        sys.stdout.write(f"{k:<{wid}}  {v}\n")
    return 0


def _fit(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from controller.cli.process import read_csv_columns
    from planner.bead import fit_profiles
    from core.errors import InputError

    cols = read_csv_columns(args.csv, PROFILE_COLUMNS)
    try:
        fits = fit_profiles(cols["x_mm"], cols["y_mm"], min_height_mm=args.min_height)
    except InputError as exc:
        raise InputError(f"{args.csv}: {exc}") from None
    out = {name: f.to_dict() for name, f in fits.items()}
    if args.json:
        emit_json(out)
        return 0
    sys.stdout.write(f"{'profile':<9}  {'width mm':>9}  {'height mm':>9}  {'area mm²':>9}  {'R²':>7}  parameters\n")
    for name, d in out.items():
        params = ", ".join(f"{k}={v:.5g}" for k, v in d["params"].items())
        sys.stdout.write(
            f"{name:<9}  {d['width_mm']:9.3f}  {d['height_mm']:9.3f}  {d['area_mm2']:9.3f}  {d['r2']:7.4f}  "
            f"{params}, centre {d['centre_mm']:.3f} mm\n"
        )
    return 0

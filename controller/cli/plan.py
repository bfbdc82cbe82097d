"""`cell plan STL --width W ...`: plan a part into a `cell-job/1` job file (docs/contract.md §3, §7)."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from controller.cli.parsing import Subcommands
from core.errors import CellError, ConfigError, InputError

if TYPE_CHECKING:  # the planner, the config loader and tqdm are imported when `cell plan` runs (start-up time)
    from tqdm import tqdm

    from core.material import Material
    from planner.five_axis import FiveAxisOptions
    from planner.weld import CellLimits

LONG_PLAN_FACES = 200_000  # above this a progress bar is shown even when stderr is not a terminal


def _perimeters(value: str) -> int | None:
    if value == "all":
        return None
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{value}' is not a number of perimeters or 'all'") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"{n}: the number of perimeters cannot be negative")
    return n


def positive_arg(value: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{value}' is not a number of mm") from None
    if not x > 0 or x != x or x == float("inf"):
        raise argparse.ArgumentTypeError(f"{value}: must be a positive number of mm")
    return x


def _allowance(value: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{value}' is not a number of mm") from None
    if not 0.0 <= x <= 100.0:
        raise argparse.ArgumentTypeError(f"{value}: must be between 0 and 100 mm")
    return x


def fraction_arg(value: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{value}' is not a fraction between 0 and 1") from None
    if not 0.0 <= x <= 1.0:
        raise argparse.ArgumentTypeError(f"{value}: must be between 0 and 1")
    return x


def register(sub: Subcommands) -> None:
    p = sub.add_parser("plan", help="slice a mesh into beads: the job file for the cell",
                       description="Plan a part (STL/OBJ/3MF) into layers of beads with their welding parameters.")
    p.add_argument("mesh", metavar="STL", help="the part's mesh (STL, OBJ or 3MF)")
    p.add_argument("--width", type=positive_arg, required=True, metavar="W", help="bead width, mm")
    p.add_argument("--layer-height", type=positive_arg, metavar="H", help="layer height, mm (default: bead height)")
    p.add_argument("--perimeters", type=_perimeters, default=2, metavar="N|all",
                   help="perimeters around every boundary (default 2), or 'all' to offset until they meet")
    p.add_argument("--units", choices=("mm", "cm", "m", "inch"), default="mm", help="unit of the mesh file (default mm)")
    p.add_argument("--material", metavar="M", help="material name or YAML file (default: cell.yaml's)")
    p.add_argument("--out", metavar="JOB", help="job file to write (default: STEM.job.json here)")
    p.add_argument("--preview", metavar="DIR", help="write layers.png and overview.png into DIR")
    p.add_argument("--allow-outside", action="store_true",
                   help="accept welding points outside the material's envelope")
    p.add_argument("--allow-underfill", action="store_true",
                   help="plan features no legal bead fills and layers below --min-coverage, with warnings")
    p.add_argument("--allow-overhang", action="store_true",
                   help="plan layers stepping out beyond the overhang rule, with warnings")
    p.add_argument("--min-coverage", type=fraction_arg, default=0.97, metavar="F",
                   help="least share of every layer covered by beads (default 0.97)")
    p.add_argument("--machining-allowance", type=_allowance, metavar="MM",
                   help="near-net: grow every layer and the top by MM of stock to machine "
                        "(default: the material's machining_allowance_mm, else 0)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--frame", choices=("substrate", "cad"), default="substrate",
                   help="substrate: the part's lowest point on z = 0 (default); cad: keep the CAD coordinates")
    p.add_argument("--no-feed-forward", dest="feed_forward", action="store_false",
                   help="one speed per bead: no per-segment speeds levelling each layer's predicted top "
                        "(docs/along-the-path.md); the job stays cell-job/1")
    p.add_argument("--five-axis", action="store_true",
                   help="tool axis per point (down-hand, within kinematics.tilt_limit_deg); nozzle collision check")
    p.set_defaults(func=run)


def _cell_values() -> dict[str, Any]:
    """What `cell plan` reads from config/cell.yaml (its material, workspace, speed and source
    limits, tilt limit and nozzle), validated; {} when there is no valid cell.yaml."""
    # on a cache miss only: pydantic and PyYAML are what a remembered start saves (issue 28)
    from core.config import load_cell

    try:
        cell = load_cell()
    except CellError:
        return {}
    lim, nz = cell.limits, cell.nozzle
    lo, hi = lim.workspace_min_mm, lim.workspace_max_mm
    return {"material": cell.cell.material,
            "room": [float(hi[0] - lo[0]), float(hi[1] - lo[1]), float(hi[2] - lo[2])],
            "limits": [lim.max_speed_mm_min, lim.min_weld_speed_mm_min, lim.source_current_max_a,
                       lim.source_wfs_max_m_min],
            "tilt_limit_deg": cell.kinematics.tilt_limit_deg,
            "nozzle": [nz.half_angle_deg, nz.length_mm, nz.standoff_mm]}


def _material_values(path: Path) -> dict[str, Any]:
    """The validated material's JSON dump and the fields its dump leaves out."""
    # on a cache miss only: pydantic and PyYAML are what a remembered start saves (issue 28)
    from core.config import load_material

    m = load_material(str(path))
    hidden = {name: getattr(m, name) for name, f in type(m).model_fields.items() if f.exclude}
    return {"dump": m.model_dump(mode="json"),
            "hidden": {k: v.model_dump(mode="json") if hasattr(v, "model_dump") else v for k, v in hidden.items()}}


def _config(material: str | None, five_axis: bool) -> tuple[Material, tuple[float, float, float] | None, CellLimits,
                                                          FiveAxisOptions | None]:
    """The material, the cell's workspace extent (a part larger than it is refused before slicing),
    its speed and source limits (a bead outside them is refused at plan time) and, for a 5-axis
    plan, its tilt limit and nozzle, from config/; the planner's defaults (cell.yaml's own)
    without a valid cell.yaml. Remembered by the files' bytes (core.config_cache)."""
    # what planning needs (after the arguments parsed): the planner's option types
    from core.config_cache import CONFIG_DIR, Frozen, material_path, remembered
    from planner.weld import CellLimits

    if five_axis:  # a 5-axis plan only: a 3-axis plan's start-up does not load planner.five_axis
        from planner.five_axis import FiveAxisOptions, Nozzle

    cell = remembered("cell-plan", [CONFIG_DIR / "cell.yaml"], _cell_values)
    path = material_path(material or cell.get("material") or "inconel718-1.0mm")
    mat = remembered("material", [path], lambda: _material_values(path))
    material_ = cast("Material", Frozen(mat["dump"], mat["hidden"]))
    if not cell:
        return material_, None, CellLimits(), FiveAxisOptions() if five_axis else None
    room = (cell["room"][0], cell["room"][1], cell["room"][2])
    five = FiveAxisOptions(tilt_limit_deg=cell["tilt_limit_deg"], nozzle=Nozzle(*cell["nozzle"])) if five_axis else None
    return material_, room, CellLimits(*cell["limits"]), five


def material_named(name: str | None) -> Material:
    """The validated material by name or path, else cell.yaml's, else Inconel 718 (`cell repair plan`)."""
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from core.config import load_cell, load_material

    if name is None:
        try:
            name = load_cell().cell.material
        except CellError:
            name = "inconel718-1.0mm"
    return load_material(name)


class _Bar:
    """tqdm on stderr, only for a terminal or a long plan; never on stdout."""

    def __init__(self, enabled: bool) -> None:
        self.bar: tqdm | None = None
        self.enabled = enabled

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self.bar is None:
            # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="layer", desc="planning", file=sys.stderr, leave=False)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run(args: argparse.Namespace) -> int:
    # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
    from controller.cli.main import emit_json
    from planner.job import job_to_json
    from planner.mesh import read_mesh
    from planner.plan import PlanOptions, plan_part

    t0 = time.perf_counter()
    material, workspace, cell_limits, five_axis = _config(args.material, args.five_axis)
    options = PlanOptions(width_mm=args.width, layer_height_mm=args.layer_height, perimeters=args.perimeters,
                          units=args.units, allow_outside=args.allow_outside,
                          allow_underfill=args.allow_underfill, allow_overhang=args.allow_overhang,
                          min_coverage=args.min_coverage, workspace_mm=workspace, cell_limits=cell_limits,
                          machining_allowance_mm=args.machining_allowance, frame=args.frame,
                          five_axis=five_axis, feed_forward=args.feed_forward)
    mesh = read_mesh(args.mesh, args.units)
    bar = _Bar(sys.stderr.isatty() or len(mesh.faces) >= LONG_PLAN_FACES)
    try:
        job = plan_part(mesh, options, material, progress=bar)
    finally:
        bar.close()
    out = Path(args.out) if args.out else Path(Path(args.mesh).stem + ".job.json")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(job_to_json(job))
    except OSError as exc:
        raise InputError(f"--out {out}: cannot write the job file ({exc.strerror or exc})") from exc
    previews: list[str] = []
    if args.preview:
        # lazy: loaded only when this subcommand runs (keeps `cell` start-up fast for the others)
        from controller.api.jobs import write_previews

        try:
            previews = [str(p) for p in write_previews(job, args.preview)]
        except OSError as exc:
            raise ConfigError(f"--preview {args.preview}: cannot write the plots ({exc.strerror or exc})") from exc
    summary = dict(job.summary)
    summary.update({"job": str(out), "previews": previews, "plan_time_s": round(time.perf_counter() - t0, 3)})
    if args.json:
        emit_json(summary)
    else:
        s = summary
        print(f"{job.source.file}: {s['layers']} layers, {s['passes']} beads ({s['arc_starts']} arc starts), "
              f"{s['deposit_length_mm'] / 1000:.2f} m of bead, {s['volume_mm3'] / 1000:.1f} cm3, "
              f"coverage {100 * s['coverage']:.1f} % (min {100 * s['coverage_min']:.1f} % at layer "
              f"{s['coverage_min_layer']}), overfill {100 * s['overfill']:.2f} %, mass balance within "
              f"{100 * s['mass_balance_max_error']:.2f} %, about {s['est_time_s'] / 60:.0f} min")
        ff = s.get("feed_forward")
        if ff and ff.get("passes_levelled"):
            print(f"  feed-forward: {ff['passes_levelled']} beads with per-segment speeds; the predicted top's spread "
                  f"along the beads at most {ff['worst_before_mm']:.2f} mm -> {ff['worst_after_mm']:.2f} mm per layer")
        mach = s.get("machining", {})
        if mach.get("allowance_mm"):
            st = mach["stock_mm"]
            print(f"  near-net: {mach['allowance_mm']:g} mm allowance; stock to machine: sides "
                  f"{st['side_min']:.2f}-{st['side_max']:.2f} mm, top {st['top']:.2f} mm, bottom {st['bottom']:.2f} mm")
        for fx in s.get("allowance_would_fix", [])[:6]:
            print(f"  buildable with --machining-allowance {fx['allowance_mm']:g}: {fx['feature'].split(' (buildable')[0]}")
        for r in s["repairs"]:
            print(f"  repaired: {r}")
        for wmsg in s["warnings"]:
            print(f"  warning: {wmsg}")
        print(f"  job file: {out}")
        for p in previews:
            print(f"  preview: {p}")
    return 0

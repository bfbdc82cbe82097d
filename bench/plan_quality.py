"""Plan quality on a set of parts built with trimesh, measured independently of the planner's summary.

Per part: the plan's verdict (planned, or the error naming what cannot be planned), then the
plan made with --allow-underfill/--allow-overhang measured against trimesh's own section of the
mesh at every layer's mid-plane: coverage, bead area outside the contour, metal laid against the
layer (mass balance), shortest pass, Ding's stable spacing, seams of single-bead walls.

Run: .venv/bin/python -m bench.plan_quality [--quick] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import shapely
import trimesh
from shapely.geometry import Point, box

from core.errors import MeshError
from planner.extrude import extrude, stack

W = 6.0  # nominal bead width (Inconel 718, 1.0 mm wire: legal widths 4.47-6.56 mm at 0.66 mm layers)


def _wall(t: float, length: float = 80.0, height: float = 20.0) -> trimesh.Trimesh:
    return extrude(box(0, 0, length, t), height)


def _pins_under_plate() -> trimesh.Trimesh:
    pins = [extrude(Point(15 + 22 * i, 15).buffer(f * W / 2, quad_segs=24), 8.0)
            for i, f in enumerate((0.8, 1.2, 1.6, 2.0))]
    return stack(*pins, extrude(box(0, 0, 100, 30), 4.0, z0=8.0))


def _l_bracket() -> trimesh.Trimesh:
    leg = 1.5 * W
    return extrude(box(0, 0, 60, leg).union(box(0, 0, leg, 60)), 15.0)


def _tilted_cylinder(angle_deg: float = 20.0) -> trimesh.Trimesh:
    """A column of round sections leaning `angle_deg` (a sheared cylinder standing on its base)."""
    m = extrude(Point(0, 0).buffer(15.0, quad_segs=24), 40.0)
    shear = np.eye(4)
    shear[0, 2] = np.tan(np.radians(angle_deg))
    m.apply_transform(shear)
    return m


def parts(quick: bool) -> list[tuple[str, trimesh.Trimesh, float]]:
    """(name, mesh, bead width) of the bench set."""
    out = [(f"wall {f:g} w", _wall(f * W), W) for f in (1.2, 1.5, 2.0, 2.5, 3.0)]
    out += [("pins 0.8-2 w under a plate", _pins_under_plate(), W),
            ("L, 1.5 w legs", _l_bracket(), W),
            ("torus", trimesh.creation.torus(major_radius=40.0, minor_radius=10.0, major_sections=96,
                                             minor_sections=48), W),
            ("tall 3 mm wall", _wall(3.0, 60.0, 60.0 if quick else 180.0), 3.0),
            ("sheared cylinder 20 deg", _tilted_cylinder(), W)]
    return out


def _section(mesh: trimesh.Trimesh, z: float):
    sec = mesh.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1])
    if sec is None:
        return shapely.Polygon()
    planar, _ = sec.to_2D(to_2D=np.eye(4))
    region = shapely.Polygon()
    for ring in planar.discrete:  # even-odd: holes cancel
        region = region.symmetric_difference(shapely.Polygon(ring).buffer(0))
    return region


def _close_fraction(layer, ratio: float, w: float) -> float:
    """Share of bead length whose centre line has another pass's centre line closer than
    `ratio` x its width (Ding's stable limit)."""
    lines = [shapely.linestrings(p.points[:, :2]) for p in layer.passes]
    if len(lines) < 2:
        return 0.0
    close = total = 0.0
    for i, ln in enumerate(lines):
        others = shapely.union_all([x for j, x in enumerate(lines) if j != i])
        d = np.arange(0.0, shapely.length(ln), 0.25 * w)
        if len(d) == 0:
            continue
        pts = shapely.line_interpolate_point(ln, d)
        # Where beads meet end to end (a scan row reaching a loop) the distance falls to 0: not a pair.
        dist = shapely.distance(pts, others)
        limit = 0.98 * ratio * layer.passes[i].width_mm
        close += float(np.sum((dist < limit) & (dist > 0.25 * w)))
        total += len(d)
    return close / total if total else 0.0


def measure(mesh: trimesh.Trimesh, job, material) -> dict:
    """Independent figures of a planned job (see the module docstring)."""
    low = mesh.bounds[0, 2]
    wire = np.pi * material.wire_diameter_mm ** 2 / 4
    min_len = material.min_bead_length_mm or 2 * job.bead.width_mm
    cov, out, mass, close, seams = [], 0.0, [], [], []
    fp_total = 0.0
    shortest = np.inf
    for layer in job.layers:
        region = _section(mesh, low + layer.z_mm - layer.height_mm / 2)
        if region.is_empty or not layer.passes:
            cov.append(0.0 if not region.is_empty else 1.0)
            continue
        fp = shapely.union_all([shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2, quad_segs=8)
                                for p in layer.passes])
        cov.append(region.intersection(fp).area / region.area)
        out += fp.difference(region).area
        fp_total += fp.area
        laid = sum(wire * p.wfs_m_min * 1000 / p.speed_mm_min * p.length_mm for p in layer.passes)
        lone = len(layer.passes) == 1 and layer.passes[0].role == "gap"
        want = region.area * layer.height_mm  # a lone bead too fills its wall's section (issue 28)
        mass.append(abs(laid - want) / want)
        shortest = min(shortest, min(p.length_mm for p in layer.passes))
        if layer.index % 5 == 0:
            close.append(_close_fraction(layer, material.bead.min_step_over_ratio, job.bead.width_mm))
        if lone and layer.passes[0].points[0].tolist() == layer.passes[0].points[-1].tolist():
            seams.append(tuple(np.round(layer.passes[0].points[0, :2], 1)))
    cov_arr = np.array(cov)
    return {"coverage_min": round(float(cov_arr.min()), 4) if len(cov_arr) else 1.0,
            "worst_layer": int(np.argmin(cov_arr)) if len(cov_arr) else 0,
            "outside": round(out / fp_total, 4) if fp_total else 0.0,
            "mass_layer_max": round(max(mass, default=0.0), 4),
            "mass_pass_max": job.summary["mass_balance_max_error"],
            "shortest_pass_mm": round(float(shortest), 2), "min_bead_length_mm": round(min_len, 2),
            "close_below_stable": round(float(np.mean(close)) if close else 0.0, 4),
            "lone_loop_seams_distinct": (len(set(seams)) / len(seams)) if seams else None}


def run_part(name: str, mesh: trimesh.Trimesh, width: float, material) -> dict:
    from planner.plan import PlanOptions, plan_part

    t0 = time.perf_counter()
    verdict = "planned"
    try:
        plan_part(mesh, PlanOptions(width_mm=width), material)
    except MeshError as exc:
        verdict = f"error: {exc}"
    t_strict = time.perf_counter() - t0
    job = plan_part(mesh, PlanOptions(width_mm=width, allow_underfill=True, allow_overhang=True), material)
    row = {"part": name, "width_mm": width, "layers": len(job.layers),
           "passes": sum(len(L.passes) for L in job.layers), "plan_s": round(t_strict, 2), "verdict": verdict,
           "warnings": len(job.summary["warnings"]), "overhang_layers": len(job.summary["overhang_layers"])}
    row.update(measure(mesh, job, material))
    return row


def check(row: dict) -> list[str]:
    """Targets: a clean plan meets every figure; a failed one names what it could not plan."""
    bad = []
    if row["verdict"] == "planned":
        if row["coverage_min"] < 0.97:
            bad.append(f"coverage {row['coverage_min']}")
        if row["outside"] > 0.03:
            bad.append(f"outside {row['outside']}")
        if row["mass_pass_max"] > 0.03 or row["mass_layer_max"] > 0.03:
            bad.append(f"mass {row['mass_pass_max']}/{row['mass_layer_max']}")
    elif "layer" not in row["verdict"]:
        bad.append("error without a layer")
    if row["shortest_pass_mm"] < row["min_bead_length_mm"] - 1e-6:
        bad.append(f"pass of {row['shortest_pass_mm']} mm")
    if row["coverage_min"] < 0.97 and row["verdict"] == "planned":
        bad.append("low coverage not reported")
    return bad


def main(argv: list[str]) -> int:
    from core.config import load_material

    ap = argparse.ArgumentParser(prog="bench.plan_quality")
    ap.add_argument("--quick", action="store_true", help="a shorter tall wall")
    ap.add_argument("--json", action="store_true", help="one JSON object per part")
    ap.add_argument("--material", default="inconel718-1.0mm")
    args = ap.parse_args(argv)
    material = load_material(args.material)
    failures = 0
    for name, mesh, width in parts(args.quick):
        row = run_part(name, mesh, width, material)
        bad = check(row)
        failures += bool(bad)
        if args.json:
            print(json.dumps({**row, "missed": bad}))
            continue
        v = row["verdict"]
        print(f"{name:28s} {row['layers']:4d} layers {row['passes']:5d} passes {row['plan_s']:6.2f} s | "
              f"cov min {100 * row['coverage_min']:5.1f} % (layer {row['worst_layer']}) | out "
              f"{100 * row['outside']:4.1f} % | mass pass {100 * row['mass_pass_max']:4.2f} % layer "
              f"{100 * row['mass_layer_max']:4.1f} % | shortest {row['shortest_pass_mm']:6.1f} mm | close<stable "
              f"{100 * row['close_below_stable']:4.1f} % | {'MISSED ' + ', '.join(bad) if bad else 'ok'}")
        print(f"    {v[:300]}")
    print(f"{failures} part(s) missed a target")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

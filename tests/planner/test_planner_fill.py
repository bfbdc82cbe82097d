"""Issue 16: every region filled with legal beads, nothing dropped silently, the metal balanced.

Small parts (a few layers each), measured against trimesh's own section of the mesh.
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import shapely
import trimesh
from shapely.geometry import Point, box

from core.config import load_material
from planner.bead import step_over
from core.errors import MeshError
from planner.extrude import extrude, stack
from planner.overhang import check_overhang, overhang_limit_mm
from planner.plan import PlanOptions, plan_part
from planner.process import inverse
from planner.thin import legal_widths

W = 6.0
MAT = load_material("inconel718-1.0mm")  # legal widths at the 0.66 mm layer: about 4.47-6.56 mm
H = inverse(MAT, W).height_mm
WIDTHS = legal_widths(MAT, H, W, step_over(W) / W, False)


def _section(mesh: trimesh.Trimesh, z: float):
    sec = mesh.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1])
    planar, _ = sec.to_2D(to_2D=np.eye(4))
    region = shapely.Polygon()
    for ring in planar.discrete:
        region = region.symmetric_difference(shapely.Polygon(ring).buffer(0))
    return region


def _footprint(layer):
    return shapely.union_all([shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2, quad_segs=8)
                              for p in layer.passes])


def _laid(p) -> float:
    return np.pi * MAT.wire_diameter_mm ** 2 / 4 * p.wfs_m_min * 1000 / p.speed_mm_min


@pytest.mark.parametrize("walls_w", [1.5, 2.0, 2.5, 3.0])
def test_walls_are_filled_by_legal_beads_with_the_metal_they_need(walls_w):
    t = walls_w * W
    mesh = extrude(box(0, 0, 60, t), 4 * H)
    job = plan_part(mesh, PlanOptions(width_mm=W), MAT)
    for layer in job.layers:
        region = _section(mesh, layer.z_mm - H / 2)
        fp = _footprint(layer)
        assert region.intersection(fp).area / region.area >= 0.97, layer.index
        assert fp.difference(region).area / fp.area <= 0.03, layer.index
        for p in layer.passes:
            assert WIDTHS.lo - 1e-6 <= p.width_mm <= WIDTHS.hi + 1e-6  # each bead inside the envelope
            assert inverse(MAT, p.width_mm, H).inside_envelope
        if len(layer.passes) > 1:  # overlapped beads: the layer's metal is the layer
            laid = sum(_laid(p) * p.length_mm for p in layer.passes)
            assert laid == pytest.approx(region.area * H, rel=0.03)
    assert job.summary["mass_balance_max_error"] <= 0.03
    assert job.summary["coverage_min"] >= 0.97
    assert job.summary["close_neighbour_max"] <= 0.1  # Ding: beads at most rarely closer than 2/3 w


def test_a_wall_no_legal_bead_count_fills_is_an_error_naming_layer_position_and_size():
    mesh = extrude(box(0, 0, 60, 1.2 * W), 2 * H)  # wider than one legal bead, narrower than two
    with pytest.raises(MeshError, match=r"layer 0: wall at \(30\.0, 3\.6\) is 7\.20 mm wide"):
        plan_part(mesh, PlanOptions(width_mm=W), MAT)
    job = plan_part(mesh, PlanOptions(width_mm=W, allow_underfill=True), MAT)
    assert job.summary["underfill_features"] == 2
    assert any("7.20 mm wide" in w for w in job.summary["warnings"])


def test_a_feature_narrower_than_the_smallest_legal_bead_is_reported_never_dropped():
    mesh = stack(extrude(box(0, 0, 60, 30), 2 * H), extrude(box(0, 40, 60, 43), 2 * H))  # a 3 mm fin
    with pytest.raises(MeshError, match=r"3\.00 mm wide, narrower than the smallest legal bead \(4\.4"):
        plan_part(mesh, PlanOptions(width_mm=W), MAT)


def test_no_layer_below_min_coverage_passes_silently():
    mesh = extrude(Point(0, 0).buffer(1.1 * W, quad_segs=32), 2 * H)
    job = plan_part(mesh, PlanOptions(width_mm=W), MAT)
    worst = job.summary["coverage_min"]
    with pytest.raises(MeshError, match="below --min-coverage"):
        plan_part(mesh, PlanOptions(width_mm=W, min_coverage=min(1.0, worst + 0.001)), MAT)
    assert job.summary["coverage_min_layer"] in (0, 1)


def test_no_pass_is_shorter_than_the_minimum_and_none_has_zero_length():
    ring = Point(0, 0).buffer(30, quad_segs=32).difference(Point(0, 0).buffer(12, quad_segs=32))
    mesh = stack(extrude(ring, 3 * H), extrude(box(40, -10, 70, 10), 3 * H))
    for per in (2, "all"):
        job = plan_part(mesh, PlanOptions(width_mm=W, perimeters=per), MAT)
        for layer in job.layers:
            for p in layer.passes:
                assert p.length_mm >= 2 * W  # min_bead_length_mm defaults to two bead widths
                assert np.all(np.linalg.norm(np.diff(p.points, axis=0), axis=1) > 0)


def test_a_pin_too_small_for_a_bead_of_the_minimum_length_is_reported():
    mesh = stack(extrude(box(0, 0, 40, 30), 2 * H), extrude(Point(60, 15).buffer(0.8 * W / 2, quad_segs=24), 2 * H))
    with pytest.raises(MeshError, match=r"layer 0: feature at \(60\.0, 15\.0\)"):
        plan_part(mesh, PlanOptions(width_mm=W), MAT)


def test_all_perimeters_fill_every_ring_and_scan_the_rest():
    ring = Point(0, 0).buffer(40, quad_segs=48).difference(Point(0, 0).buffer(27, quad_segs=48))
    mesh = stack(extrude(ring, 2 * H), extrude(box(60, -20, 100, 20), 2 * H))
    job = plan_part(mesh, PlanOptions(width_mm=W, perimeters="all"), MAT)
    for layer in job.layers:
        region = _section(mesh, layer.z_mm - H / 2)
        fp = _footprint(layer)
        assert region.intersection(fp).area / region.area >= 0.97
        assert fp.difference(region).area / fp.area <= 0.03


def test_scan_rows_sit_d_star_from_the_last_perimeter_and_apart():
    mesh = extrude(box(0, 0, 80, 60), H)
    # the rows' places (the feed-forward splits the links between rows into points of their own)
    job = plan_part(mesh, PlanOptions(width_mm=W, perimeters=1, feed_forward=False), MAT)
    d = step_over(W)
    layer = job.layers[0]
    rows = sorted({round(float(y), 3) for p in layer.passes for (x, y, z) in p.points
                   if W / 2 + 0.5 < y < 60 - W / 2 - 0.5 and W / 2 + 1 < x < 80 - W / 2 - 1})
    assert rows[0] == pytest.approx(W / 2 + d, abs=0.01)  # first row d* inside the loop's centre line
    gaps = np.diff(rows)
    assert np.all(gaps >= MAT.bead.min_step_over_ratio * W - 1e-6)  # no pair closer than the stable limit
    assert np.all(gaps <= W)


def test_single_bead_loops_start_at_a_new_point_every_layer():
    ring = Point(0, 0).buffer(25, quad_segs=48).difference(Point(0, 0).buffer(20, quad_segs=48))
    job = plan_part(extrude(ring, 6 * H), PlanOptions(width_mm=W), MAT)
    starts = [tuple(np.round(L.passes[0].points[0, :2], 1)) for L in job.layers]
    assert all(len(L.passes) == 1 for L in job.layers)
    assert len(set(starts)) == len(starts)


def test_overhang_beyond_the_rule_fails_naming_the_layer():
    mesh = stack(extrude(box(0, 0, 40, 40), 4 * H), extrude(box(0, 0, 70, 40), 2 * H, z0=4 * H))
    with pytest.raises(MeshError, match=r"overhang rule.*layer 4: steps out 30\.00 mm"):
        plan_part(mesh, PlanOptions(width_mm=W), MAT)
    job = plan_part(mesh, PlanOptions(width_mm=W, allow_overhang=True), MAT)
    assert job.summary["overhang_layers"] == [4]


def test_overhang_check_is_a_pure_function_a_tilted_torch_can_relax():
    below, above = box(0, 0, 40, 40), box(0, 0, 41, 40)  # a 1 mm step out at 0.66 mm per layer
    assert overhang_limit_mm(0.66, W, 30.0) == pytest.approx(0.66 * np.tan(np.radians(30)))
    assert not check_overhang(below, above, 0.66, W, 30.0).ok
    assert check_overhang(below, above, 0.66, W, 30.0, tilt_deg=30.0).ok
    assert check_overhang(None, above, 0.66, W, 30.0).ok  # the substrate carries layer 0


def test_overfill_is_measured_against_the_contour_itself():
    mesh = extrude(Point(0, 0).buffer(1.3 * W, quad_segs=32), 2 * H)  # a pin of 2.6 w: loop + centre
    job = plan_part(mesh, PlanOptions(width_mm=W, allow_underfill=True), MAT)
    layer = job.layers[0]
    region = _section(mesh, layer.z_mm - H / 2)
    fp = _footprint(layer)
    assert job.summary["overfill"] == pytest.approx(fp.difference(region).area / fp.area, abs=0.02)


def test_a_triangle_soup_is_an_error_not_an_empty_plan():
    rng = np.random.default_rng(1)
    soup = trimesh.Trimesh(**trimesh.triangles.to_kwargs(rng.uniform(0, 50, (200, 3, 3))), process=False)
    with pytest.raises(MeshError, match="no layer has a closed region"):
        plan_part(soup, PlanOptions(width_mm=W), MAT)


@pytest.mark.parametrize("units, scale", [("cm", 0.1), ("m", 0.001)])
def test_parts_in_cm_and_m_are_scaled(units, scale):
    mesh = extrude(box(0, 0, 60 * scale, 40 * scale), 3 * H * scale)
    job = plan_part(mesh, PlanOptions(width_mm=W, units=units), MAT)
    assert job.source.units == units and len(job.layers) == 3
    xs = np.concatenate([p.points[:, 0] for p in job.layers[0].passes])
    assert xs.max() - xs.min() == pytest.approx(60 - W, abs=0.5)


def test_cell_plan_starts_without_the_geometry_libraries(tmp_path):
    code = ("import sys; from controller.cli.main import build_parser\n"
            "try:\n    build_parser(['plan', '--help']).parse_args(['plan', '--help'])\n"
            "except SystemExit:\n    pass\n"
            "print(sorted(m for m in ('numpy', 'shapely', 'scipy', 'trimesh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"
    stl = tmp_path / "block.stl"
    stl.write_bytes(extrude(box(0, 0, 30, 30), 2.0).export(file_type="stl"))
    code = ("import sys\n"
            "from core.config import load_material; from planner.plan import PlanOptions, plan_part\n"
            f"plan_part({str(stl)!r}, PlanOptions(width_mm=6.0), load_material('inconel718-1.0mm'))\n"
            "print('scipy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"  # a plain block plans without importing scipy


def test_a_junction_does_not_widen_every_arm_of_a_thin_cross():
    cross = extrude(box(-40, -2.6, 40, 2.6).union(box(-2.6, -40, 2.6, 40)), 2 * H)  # 5.2 mm arms
    job = plan_part(cross, PlanOptions(width_mm=W), MAT)
    layer = job.layers[0]
    assert all(p.width_mm == pytest.approx(5.2, abs=0.1) for p in layer.passes)
    region = _section(cross, layer.z_mm - H / 2)
    fp = _footprint(layer)
    assert region.intersection(fp).area / region.area >= 0.97
    assert fp.difference(region).area / fp.area <= 0.03


def test_the_legs_of_an_l_get_their_beads_at_the_step_over_not_the_corners_width():
    """Issue 29: the corner of an L of 11 mm legs holds a 12.9 mm circle; a layout for it put the legs'
    two loops 5.5 mm apart with 5.5 mm beads (a crevice between them) and a third bead in the corner."""
    ell = extrude(box(0, 0, 60, 11).union(box(0, 0, 11, 50)), 2 * H)
    job = plan_part(ell, PlanOptions(width_mm=W), MAT)
    for layer in job.layers:
        lines = [shapely.linestrings(p.points[:, :2]) for p in layer.passes]
        for cut in (shapely.linestrings([(40, -1), (40, 12)]), shapely.linestrings([(-1, 30), (12, 30)])):
            hits = sorted(c for ln in lines for c in np.atleast_2d(shapely.get_coordinates(ln.intersection(cut)))
                          .tolist() if c)
            assert len(hits) == 2, (layer.index, hits)
            gap = float(np.hypot(*np.subtract(hits[1], hits[0])))
            w = max(p.width_mm for p in layer.passes)
            assert WIDTHS.r_lo * w * 0.99 <= gap <= WIDTHS.r_hi * w * 1.01, (layer.index, gap, w)


def test_teeth_of_a_comb_keep_ding_spacing():
    comb = extrude(box(0, 0, 80, 10).union(box(0, 0, 5, 40)).union(box(40, 0, 49, 40))
                   .union(box(60, 0, 71, 40)), 2 * H)
    job = plan_part(comb, PlanOptions(width_mm=W), MAT)
    assert job.summary["close_neighbour_max"] <= 0.05
    assert job.summary["coverage_min"] >= 0.97

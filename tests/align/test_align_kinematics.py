"""Padathu 2005 transform (Table 1, the cos(phi) typo), trunnion kinematics, applying alignments."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from controller.motion.kinematics import (Trunnion, apply_to_job, apply_to_mesh, apply_transform, paper_matrices,
                                         paper_transform, rotation_about_pivot, rotation_matrix, unit)
from controller.align.leveling import face_angle, leveling_angles
from core.errors import InputError
from controller.job.read import job_from_dict
from tests.jobs import PassSpec, job_object

TABLE1_PRE = np.array([[0, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0]], dtype=float)
TABLE1_POST = np.array([[2.53553, 0.41421, -1.46447], [2.03553, 1.12132, -0.96447],
                        [2.5355, 1.8284, -1.4645], [3.0355, 1.1213, -1.9645]])


def test_paper_table1_reproduced():
    got = paper_transform(TABLE1_PRE, 45.0, 45.0, (1, 1, 5))
    # The paper prints 4-6 significant digits: the printed value's own rounding is ≤ 5e-5.
    assert np.abs(got - TABLE1_POST).max() < 1e-4
    same = apply_transform(rotation_about_pivot([("z", 45), ("y", 45)], (1, 1, 5)), TABLE1_PRE)
    assert np.abs(same - got).max() < 1e-12


def _typo_transform(p, a_deg, b_deg, pivot):
    """The appendix verbatim: RB[2,2] = cos(phi)."""
    phi = np.radians(a_deg)
    ra, rb = paper_matrices(a_deg, b_deg)
    rb = rb.copy()
    rb[2, 2] = np.cos(phi)
    t = np.eye(4)
    t[:3, 3] = pivot
    w0 = np.eye(4)
    w0[:3, 3] = -np.asarray(pivot)
    return apply_transform(w0 @ rb @ ra @ t, p)


def test_a_not_equal_b_exposes_the_appendix_typo():
    a, b, pivot = 30.0, 60.0, (1.0, 1.0, 5.0)
    fixed = paper_transform(TABLE1_PRE, a, b, pivot)
    typo = _typo_transform(TABLE1_PRE, a, b, pivot)
    expected = apply_transform(rotation_about_pivot([("z", a), ("y", b)], pivot), TABLE1_PRE)
    assert np.abs(fixed - expected).max() < 1e-12
    assert np.abs(typo - fixed).max() > 0.5  # the typo moves the points by mm
    # A rigid motion keeps lengths; with the typo a unit step along z is no longer 1 mm long.
    ends = np.array([[0, 0, 0], [0, 0, 1.0]])
    d_fixed = np.linalg.norm(np.diff(paper_transform(ends, a, b, pivot), axis=0))
    d_typo = np.linalg.norm(np.diff(_typo_transform(ends, a, b, pivot), axis=0))
    assert d_fixed == pytest.approx(1.0, abs=1e-12)
    assert abs(d_typo - 1.0) > 0.05
    # With A = B the typo is invisible, which is why Table 1 did not show it.
    assert np.abs(_typo_transform(TABLE1_PRE, 45, 45, pivot) - paper_transform(TABLE1_PRE, 45, 45, pivot)).max() < 1e-12


@pytest.mark.parametrize("table,axis_a,axis_second", [
    ("AB", (1, 0, 0), (0, 1, 0)),
    ("AC", (1, 0, 0), (0, 0, 1)),
    ("AB", (0, 0, 1), (0, 1, 0)),       # the paper's own axes: A about z, B about y
    ("AB", (-1, 0, 0), (0, 1, 0)),      # reversed axis direction
])
def test_forward_inverse_roundtrip_random_poses(table, axis_a, axis_second):
    t = Trunnion(table=table, pivot=(12.0, -30.0, 85.0), axis_a=axis_a, axis_second=axis_second,
                 offset=(0.0, 4.0, -7.5), a_limits_deg=(-120, 120), second_limits_deg=(-360, 360))
    rng = np.random.default_rng(42)
    worst_p = worst_v = worst_ax = 0.0
    for _ in range(300):
        p = rng.uniform(-100, 100, 3)
        v = unit(rng.normal(size=3) + np.array([0, 0, 3.0]))  # within ~90° of +Z: reachable
        axes = t.inverse(p, v)
        # The table really turns the tool direction onto +Z.
        assert t.matrix(axes[3], axes[4])[:3, :3] @ v == pytest.approx([0, 0, 1], abs=1e-12)
        p2, v2 = t.forward(axes)
        worst_p = max(worst_p, float(np.abs(p2 - p).max()))
        worst_v = max(worst_v, float(np.abs(v2 - v).max()))
        axes2 = t.inverse(p2, v2)
        worst_ax = max(worst_ax, float(np.abs(axes2 - axes).max()))
    assert worst_p < 1e-9 and worst_v < 1e-9 and worst_ax < 1e-9


def test_paper_convention_in_trunnion_ab_with_paper_axes():
    """Trunnion AB with A about z and B about y, offset 0, is exactly the paper's transform."""
    t = Trunnion(table="AB", pivot=(1, 1, 5), axis_a=(0, 0, 1), axis_second=(0, 1, 0))
    got = apply_transform(t.matrix(45, 45), TABLE1_PRE)
    assert np.abs(got - TABLE1_POST).max() < 1e-4
    got2 = apply_transform(t.matrix(30, 60), TABLE1_PRE)
    assert np.abs(got2 - paper_transform(TABLE1_PRE, 30, 60, (1, 1, 5))).max() < 1e-12


def test_leveling_angles_bring_normal_to_z_and_are_the_small_solution():
    for ta, tb in [(0.8, -0.5), (-3.0, 7.0), (20.0, -15.0), (0.0, 0.0)]:
        n = rotation_matrix("x", ta) @ rotation_matrix("y", tb) @ np.array([0, 0, 1.0])
        lev = leveling_angles(n)
        assert lev.rotation @ n == pytest.approx([0, 0, 1], abs=1e-12)
        # A about x then B about y undoes a tilt composed as R_x(ta)·R_y(tb) exactly.
        assert lev.a_deg == pytest.approx(-ta, abs=1e-9)
        assert lev.b_deg == pytest.approx(-tb, abs=1e-9)
    # Closed form for A about x, B about y.
    n = unit([0.03, -0.05, 1.0])
    lev = leveling_angles(n)
    assert lev.a_deg == pytest.approx(np.degrees(np.arctan2(n[1], n[2])), abs=1e-9)
    assert lev.b_deg == pytest.approx(np.degrees(np.arctan2(-n[0], np.hypot(n[1], n[2]))), abs=1e-9)


def test_leveling_outside_limits_is_an_error():
    t = Trunnion(a_limits_deg=(-10, 10), second_limits_deg=(-10, 10))
    with pytest.raises(InputError, match="limits"):
        leveling_angles(unit([0.0, -1.0, 1.0]), t)  # needs A = -45°


def test_face_angle_eq1_and_cad_rotation():
    cad = np.array([1.0, 0, 0])
    fitted = rotation_matrix("z", 1.5) @ cad
    fa = face_angle(fitted, cad)
    assert fa.angle_deg == pytest.approx(1.5, abs=1e-9)
    assert fa.signed_deg == pytest.approx(1.5, abs=1e-9)
    assert fa.residual_deg == pytest.approx(0.0, abs=1e-9)
    assert fa.cad_rotation[:3, :3] @ cad == pytest.approx(fitted, abs=1e-12)
    fa2 = face_angle(rotation_matrix("z", -2.25) @ cad, cad)
    assert fa2.signed_deg == pytest.approx(-2.25, abs=1e-9) and fa2.angle_deg == pytest.approx(2.25, abs=1e-9)


def test_apply_to_job_moves_points_and_rotates_normals():
    src = job_object([[PassSpec([[0, 0, 0], [1, 0, 0]], normals=[[1, 0, 0], [0, 1, 0]])]])
    job = job_from_dict(src)
    m = rotation_about_pivot([("z", 90)], (0, 0, 0))
    m[:3, 3] = [10, 0, 0]
    out = apply_to_job(job, m)
    ps = out.layers[0].passes[0]
    assert np.allclose(ps.points, [[10, 0, 0], [10, 1, 0]])
    assert ps.normals is not None and np.allclose(ps.normals, [[0, 1, 0], [-1, 0, 0]])  # rotated, not translated
    assert out.alignment is not None and np.allclose(out.alignment.transform, m)
    assert job.layers[0].passes[0].points[1].tolist() == [1, 0, 0] and job.alignment is None  # the input is untouched
    assert src["layers"][0]["passes"][0]["points"][1] == [1, 0, 0] and "alignment" not in src
    assert out.hash != job.hash   # a new job: its own run directory and journal
    with pytest.raises(InputError, match="already carries an alignment"):
        apply_to_job(out, m)


def test_apply_to_mesh_returns_moved_copy():
    box = trimesh.creation.box(extents=(10, 10, 2))
    m = rotation_about_pivot([("x", 90)], (0, 0, -1))
    moved = apply_to_mesh(box, m)
    assert np.allclose(box.bounds, [[-5, -5, -1], [5, 5, 1]])
    assert np.allclose(moved.vertices, apply_transform(m, box.vertices))

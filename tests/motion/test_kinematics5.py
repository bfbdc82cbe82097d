"""One rotation-order convention (docs/kinematics.md): the math and the CNC simulator agree."""
from __future__ import annotations

import numpy as np
import pytest

from controller.motion.kinematics import Trunnion
from controller.motion.post5 import Post5, inverse_time, weld_axes
from core.errors import InputError
from sims.table_kin import TableKin

TABLES = {
    "AB": dict(table="AB", pivot=(5.0, -3.0, 40.0), axis_a=(1.0, 0.0, 0.0), axis_second=(0.0, 1.0, 0.0),
               offset=(0.0, 0.0, 12.0)),
    "AC": dict(table="AC", pivot=(-2.0, 4.0, 60.0), axis_a=(1.0, 0.0, 0.0), axis_second=(0.0, 0.0, 1.0),
               offset=(0.0, 3.0, 25.0)),
}


def _sim_forward(kin: TableKin, m5: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's own forward kinematics: machine axes → (part point, tool axis in the part)."""
    inv = np.linalg.inv(kin.matrix(m5[3], m5[4]))
    return inv[:3, :3] @ m5[:3] + inv[:3, 3], inv[:3, :3] @ np.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize("table", ["AB", "AC"])
def test_forward_of_inverse_is_identity_with_the_simulators_convention(table: str) -> None:
    spec = TABLES[table]
    tr = Trunnion(**spec, a_limits_deg=(-120, 120), second_limits_deg=(-360, 360))
    kin = TableKin(spec["table"], spec["pivot"], spec["axis_a"], spec["axis_second"], spec["offset"])
    rng = np.random.default_rng(18)
    worst_p = worst_a = 0.0
    for _ in range(300):
        p = rng.uniform(-50, 50, 3)
        v = rng.normal(size=3)
        v[2] = abs(v[2]) + 0.2  # tool axes the tilt limits allow (upper hemisphere)
        v /= np.linalg.norm(v)
        m5 = tr.inverse(p, v)
        q, ax = _sim_forward(kin, m5)
        worst_p = max(worst_p, float(np.abs(q - p).max()))
        worst_a = max(worst_a, float(np.abs(ax - v).max()))
    assert worst_p < 1e-9 and worst_a < 1e-9, (worst_p, worst_a)


def test_ac_order_is_c_inner_a_outer() -> None:
    """A/C: the C plate rides on the A trunnion, so C turns the part first (R_A·R_C)."""
    kin = TableKin("AC", (0, 0, 0), (1, 0, 0), (0, 0, 1), (0, 0, 0))
    m = kin.matrix(90.0, 90.0)
    # +x on the part: C turns it to +y, then A (about x) turns +y to +z
    assert np.allclose(m[:3, :3] @ [1, 0, 0], [0, 0, 1], atol=1e-12)


def test_post_processing_is_continuous_through_the_singularity() -> None:
    """A/C table, tool axis sweeping across vertical: C never jumps 180°/360°; A stays small."""
    tr = Trunnion(**TABLES["AC"])
    t = np.linspace(-1, 1, 201)
    axes = np.column_stack([0.3 * t, 0.02 + 0 * t, np.ones_like(t)])  # passes 1.1° from vertical
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    # a full turn around the vertical at 30° tilt: C runs through 360° without wrapping back
    phi = np.radians(np.linspace(0, 360, 181))
    ring = np.column_stack([0.5 * np.cos(phi), 0.5 * np.sin(phi), np.full_like(phi, np.sqrt(0.75))])
    post = Post5(tr)
    for ax in (axes, ring):
        ang = post.angles(ax)
        jumps = np.abs(np.diff(ang, axis=0)).max(axis=0)
        planned = np.degrees(np.arccos(np.clip((ax[1:] * ax[:-1]).sum(axis=1), -1, 1))).max()
        assert jumps[0] <= max(2 * planned, 1e-6) + 1e-6  # A changes with the tilt
        assert jumps[1] < 120.0 if ax is axes else jumps[1] < 3.0  # C: never a flip
    kin = TableKin("AC", TABLES["AC"]["pivot"], (1, 0, 0), (0, 0, 1), TABLES["AC"]["offset"])
    m = post.machine(np.zeros((len(ring), 3)), ring)
    for row, ax in zip(m, ring):
        assert np.allclose(_sim_forward(kin, row)[1], ax, atol=1e-9)


def test_points_outside_the_axis_limits_are_refused_naming_the_point() -> None:
    tr = Trunnion(table="AB", a_limits_deg=(-30, 30), second_limits_deg=(-30, 30))
    axes = np.array([[0, 0, 1.0], [0, np.sin(np.radians(20)), np.cos(np.radians(20))],
                     [0, np.sin(np.radians(50)), np.cos(np.radians(50))]])
    with pytest.raises(InputError, match="point 2"):
        Post5(tr).angles(axes)


def test_inverse_time_feed_gives_the_planned_tip_speed() -> None:
    pts = np.array([[0, 0, 0], [2.0, 0, 0], [2.0, 0.5, 0]])
    f = inverse_time(pts, 600.0)
    assert np.allclose(1.0 / f * 60.0, [0.2, 0.05])  # seconds per move = length / speed


def test_weld_axes_follow_the_build_subdivision() -> None:
    from controller.job.weld_path import weld_points

    pts = [[0, 0, 0], [3.0, 0, 0], [3.0, 0, 0], [3.0, 2.5, 0]]
    axes = [[0, 0, 1], [1, 0, 1], [1, 0, 1], [0, 1, 1]]
    assert len(weld_axes(pts, axes, 1.0)) == len(weld_points(pts, 1.0))


# --- chord tolerance (issue 29): the machine interpolates each axis linearly --------------------


def _bowing_pass(table: str, r0: float = 45.0, r1: float = 88.0, step: float = 2.0, dc_deg: float = -8.75):
    """A straight pass 45–88 mm from the inner rotary axis (tangent to a circle about it at 45 mm)
    whose tool axis turns about it by `dc_deg` per `step` mm (30° tilt): the table's inner axis
    turns that much per move."""
    span = float(np.sqrt(r1 * r1 - r0 * r0))
    n = int(round(span / step)) + 1
    y = np.linspace(0.0, span, n)
    c = np.array([2.0, -1.0, 2.0])   # where the inner axis of TABLES[...] passes (−P + offset)
    pts = np.column_stack([np.full(n, r0), y, np.zeros(n)]) + c
    az = np.radians(dc_deg) * np.arange(n)
    t = np.radians(30.0)
    if table == "AC":   # inner axis C about z: the axis' azimuth turns about z
        axes = np.column_stack([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), np.full(n, np.cos(t))])
    else:               # inner axis A about x: the axis turns in the y-z plane
        axes = np.column_stack([np.full(n, np.sin(t) * 0.2), np.sin(t) * np.cos(az) - 0.5, np.full(n, 0.9)])
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return pts, axes


def _worst(tr: Trunnion, pts: np.ndarray, m: np.ndarray) -> float:
    from controller.motion.post5 import tip_path

    from bench.five_axis import _seg_dist

    q = np.array([p for k in range(len(m) - 1) for p in tip_path(tr, m[k], m[k + 1], (0.25, 0.5, 0.75))])
    return float(_seg_dist(q, pts[:-1], pts[1:]).max())


@pytest.mark.parametrize("table", ["AB", "AC"])
def test_linearised_moves_keep_the_tool_tip_within_the_chord_tolerance(table: str) -> None:
    from controller.motion.lines5 import fit_lines, serial_min_s
    from controller.motion.post5 import move_line

    tr = Trunnion(**TABLES[table], a_limits_deg=(-120, 120), second_limits_deg=(-360, 360))
    pts, axes = _bowing_pass(table)
    post = Post5(tr)
    m = post.machine(pts, axes)
    before = _worst(tr, pts, m)
    if table == "AC":
        assert before > 0.15, before   # the figure: up to 0.196 mm off the path
    speeds = np.full(len(pts) - 1, 10.0)
    lines = fit_lines(post, pts, axes, m, speeds, 0.016, serial_min_s("XYZA" + table[1], 115200))
    fm, seg = lines.machine, lines.seg
    # the G-code as sent (3 decimals), read back through the forward kinematics
    sent = np.array([[float(w[1:]) for w in move_line(r, "XYZA" + table[1]).split()[1:]] for r in fm])
    assert _worst(tr, pts, sent) <= 0.02, (_worst(tr, pts, sent), before)
    # the line ends run along the pass from its first point to its last, each on the planned path
    assert np.allclose(lines.part[0], pts[0]) and np.allclose(lines.part[-1], pts[-1])
    assert (np.diff(lines.at) > 0).all() and (np.diff(seg) >= 0).all()
    from bench.five_axis import _seg_dist
    assert _seg_dist(lines.part, pts[:-1], pts[1:]).max() < 1e-9
    # inverse time: the lines' times add up to the planned time; each lasts twice its serial time
    move_s = np.linalg.norm(np.diff(pts, axis=0), axis=1) / speeds
    assert abs(lines.times(move_s).sum() - move_s.sum()) < 1e-9
    mins = serial_min_s("XYZA" + table[1], 115200)
    assert (lines.times(move_s) >= [mins(a, b) - 1e-12 for a, b in zip(fm[:-1], fm[1:])]).all()


def test_a_resumed_weld_starts_mid_move_and_maps_progress_to_planned_points() -> None:
    import asyncio

    from controller.job.read import job_from_dict
    from controller.motion.cnc5 import Five

    tr = Trunnion(**TABLES["AC"], a_limits_deg=(-120, 120), second_limits_deg=(-360, 360),
                  chord_tolerance_mm=0.02)
    pts, axes = _bowing_pass("AC")
    job = job_from_dict({
        "schema": "cell-job/1", "source": {"file": "bow.stl", "sha256": "0" * 64, "units": "mm"}, "material": {},
        "bead": {"width_mm": 3.0, "height_mm": 1.0, "step_over_mm": 2.2, "model": "tangent"},
        "layers": [{"index": 0, "z_mm": float(pts[0][2]), "height_mm": 1.0, "passes": [
            {"role": "perimeter", "width_mm": 3.0, "current_a": 120.0, "speed_mm_min": 600.0, "wfs_m_min": 5.5,
             "points": pts.tolist(), "axes": axes.tolist()}]}]})
    five = Five(tr)
    asyncio.run(five.post_job(job, 2.0))
    five.use(0, 0)
    mid = 0.5 * (pts[3] + pts[4])
    five.approach_lines(tuple(mid), 10.0, 300.0)
    lines = five.weld_lines(3, 600.0)
    assert lines[0] == "G93" and lines[-1] == "G94"
    m = [five.start]
    for g in lines[1:-1]:   # axis words are modal: a line leaves out what does not move
        row = m[-1].copy()
        for w in g.split()[1:-1]:
            row["XYZAC".index(w[0])] = float(w[1:])
        m.append(row)
    m = np.array(m)
    assert _worst(tr, pts, m) <= 0.02
    got: list[int] = []
    track, t0, cb = five.track(3, lambda j, k: got.append(j))
    assert t0 == 0 and len(track) == len(m)
    for j in range(len(track)):
        cb(j, j)
    assert got == list(range(4, len(pts)))   # each planned point once, in order, none before the start

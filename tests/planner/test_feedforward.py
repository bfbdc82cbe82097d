"""The planner's feed-forward along the path (docs/along-the-path.md): per-segment speeds that level
each layer's predicted top, every bead keeping its metal, the same job for the same input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from core.config import load_material
from planner.feedforward import Envelope, FeedForwardOptions, level_layer, predicted_tops
from planner.job import Pass, job_to_json
from planner.options import PlanOptions
from planner.plan import plan_part

ENV = Envelope(speed_min=30.0, speed_max=6000.0, wfs_min=4.0, wfs_max=7.4)
WIRE = 1.0


def _loop(points: np.ndarray, speed: float, wfs: float = 6.9) -> Pass:
    pts = np.column_stack([points, np.full(len(points), 0.77)])
    return Pass("perimeter", 7.0, 151.0, speed, wfs, pts)


def _narrowing_layer() -> tuple[Pass, ...]:
    """A square ring around a round one, 2 mm apart at the sides' middles (7 mm beads: they overlap)
    and 12 mm at the corners: the region between them narrows and widens, as in the demo part."""
    sq = np.array([[8.7, 8.7], [61.3, 8.7], [61.3, 61.3], [8.7, 61.3], [8.7, 9.2]])
    th = np.linspace(0.0, 2 * math.pi, 97)[:-1]
    circle = np.column_stack([35 + 24.3 * np.cos(th), 35 + 24.3 * np.sin(th)])
    return (_loop(circle, 1500.0), _loop(sq, 1600.0))


def _metal(p: Pass) -> float:
    return float(np.sum(p.wire_feeds() / p.speeds() * p.segment_lengths()))


def test_a_narrowing_region_is_levelled_and_every_bead_keeps_its_metal() -> None:
    layer = _narrowing_layer()
    out, lvl = level_layer(layer, WIRE, ENV)
    assert lvl.passes_levelled == 2 and lvl.spread_after_mm < 0.6 * lvl.spread_before_mm
    sq = out[1]
    assert sq.per_segment and len(sq.points) > len(layer[1].points)       # split to carry the speeds
    for before, after in zip(layer, out):
        assert _metal(after) == pytest.approx(_metal(before), rel=0.03)   # mass balance per bead
        np.testing.assert_allclose(before.points[[0, -1]], after.points[[0, -1]])
    # where the square ring runs closest to the round one it goes faster than at its corners
    mid = np.argmin(np.abs(sq.points[:-1, 0] - 35.0) + np.abs(sq.points[:-1, 1] - 8.7))
    corner = np.argmin(np.hypot(sq.points[:-1, 0] - 61.3, sq.points[:-1, 1] - 8.7))
    assert sq.speeds()[mid] > 1.15 * sq.speeds()[corner]
    tops = predicted_tops(out, WIRE)
    raw = predicted_tops(layer, WIRE)
    assert np.ptp(np.concatenate(tops)) < np.ptp(np.concatenate(raw))


def test_a_lone_beads_ends_run_slower_than_its_middle() -> None:
    line = np.column_stack([np.linspace(0, 60, 13), np.zeros(13)])
    (p,), lvl = level_layer((_loop(line, 1200.0),), WIRE, ENV, FeedForwardOptions(min_gain_mm=0.0))
    v = p.speeds()
    assert lvl.spread_after_mm < lvl.spread_before_mm
    assert v[0] < 0.9 * np.median(v) and v[-1] < 0.9 * np.median(v)


def test_the_speeds_stay_inside_the_cells_limits_and_the_envelope() -> None:
    tight = Envelope(speed_min=1300.0, speed_max=1700.0, wfs_min=6.0, wfs_max=7.4)
    out, _ = level_layer(_narrowing_layer(), WIRE, tight)
    for p in out:
        assert p.speeds().min() >= 1300.0 and p.speeds().max() <= 1700.0
        assert p.wire_feeds().min() >= 6.0 - 1e-9 and p.wire_feeds().max() <= 7.4 + 1e-9
    assert any(p.seg_wfs_m_min is not None for p in out)   # where the speed could not, the wire feed did


def test_a_plan_is_cell_job_2_with_the_spread_in_its_summary_and_the_same_bytes_twice() -> None:
    mat = load_material("inconel718-1.0mm")
    wall = trimesh.creation.box(extents=(60.0, 7.0, 2.4))
    a = plan_part(wall, PlanOptions(width_mm=7.0), mat)
    b = plan_part(wall, PlanOptions(width_mm=7.0), mat)
    assert job_to_json(a) == job_to_json(b)
    ff = a.summary["feed_forward"]
    assert len(ff["spread_before_mm"]) == len(a.layers) and ff["worst_after_mm"] < ff["worst_before_mm"]
    assert b'"schema":"cell-job/2"' in job_to_json(a)
    off = plan_part(wall, PlanOptions(width_mm=7.0, feed_forward=False), mat)
    assert b'"schema":"cell-job/1"' in job_to_json(off) and "feed_forward" not in off.summary

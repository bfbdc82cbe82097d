"""The path loop's pure half (issue 35, docs/closed-loop.md "Along the path"): fields by position,
binning, and the learning law levelling a top whose local gain differs along the path."""
from __future__ import annotations

import numpy as np
import pytest

from controller.runtime.path_plan import (
    Field, PathLaw, bin_samples, bounded_metal, plan_factors, process_for, resample, rise_ratio, spots_along, spread_reports,
)
from core.config import load_material
from planner.pour import BeadLaw

_R = load_material("inconel718-1.0mm").ribeiro
LAW = BeadLaw(_R.k1, _R.k2, _R.k3, _R.i_min_a, _R.i_max_a, _R.wfs_min_m_min, _R.wfs_max_m_min)


def test_resample_keeps_every_point_and_caps_the_segments():
    pts = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 1.0], [10.0, 3.0, 1.0]])
    out, idx = resample(pts, 3.5)
    assert len(out) == 1 + 3 + 1
    assert np.allclose(out[[0, 3, 4]], pts)
    assert np.hypot(*np.diff(out[:, :2], axis=0).T).max() <= 3.5 + 1e-9
    assert idx[3] == pytest.approx(1.0) and idx[-1] == pytest.approx(2.0)


def test_samples_binned_by_position_not_by_arrival():
    samples = [(s, 100.0 + (10.0 if s > 50 else 0.0)) for s in np.linspace(0, 99.9, 300)]
    bins = bin_samples(samples[::-1], 100.0, 7.0)           # order does not matter
    assert len(bins) == 14
    assert bins[0][1] == pytest.approx(100.0) and bins[-1][1] == pytest.approx(110.0)
    assert bins[0][0] == pytest.approx(3.5, abs=0.2)                # where its samples were
    assert sum(n for *_, n in bins) == 300


def test_a_field_is_a_kernel_mean_and_empty_far_from_its_samples():
    f = Field.of([[0.0, 0.0, 1.0], [1.0, 0.0, 3.0]])
    v = f.at(np.array([[0.5, 0.0], [50.0, 0.0]]), 2.0)
    assert v[0] == pytest.approx(2.0) and np.isnan(v[1])


def test_spots_along_a_pass_reach_its_ends():
    pts = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    sp = spots_along(pts, 10.0, 1.75)
    xs = [float(p[0]) for p in sp]
    assert xs[0] == pytest.approx(1.75) and xs[-1] == pytest.approx(38.25) and len(xs) == 5


def _run(layers: int, law: PathLaw, noise: float = 0.0, seed: int = 1) -> list[float]:
    """A wall 100 mm long laid on positions x; its local gain is 1.25 on the last quarter and 0.8
    at the ends (a run-down): the rise at x is g(x)·h/m(x). The spread of the top after each layer."""
    rng = np.random.default_rng(seed)
    x = np.arange(1.75, 100.0, 3.5)
    xy = np.c_[x, np.zeros_like(x)]
    g = np.where(x > 75, 1.25, 1.0) * np.where((x < 5) | (x > 95), 0.85, 1.0)
    h, top, m = 0.77, np.zeros_like(x), np.ones_like(x)
    fields: list[tuple[Field, Field]] = []
    spread = []
    for _ in range(layers):
        top = top + g * h / m
        meas = top + rng.normal(0.0, noise, len(x))
        d = Field(xy, meas - meas.mean())
        fields = (fields + [(d, Field(xy, m.copy()))])[-2:]
        m, _need = plan_factors(xy, np.full(len(x), 3.5), fields[-1][0], fields[-2][0] if len(fields) > 1 else None,
                                fields[-1][1], h * float(np.mean(g)), law)
        spread.append(float(top.max() - top.min()))
    return spread


def test_the_law_levels_a_top_whose_gain_differs_along_the_path():
    open_loop = _run(20, PathLaw(kp=0.0, ki=0.0))
    closed = _run(20, PathLaw(filter_mm=7.0))
    assert open_loop[-1] > 4.0                                   # open: the region and the ends run away
    assert max(closed[8:]) < 0.4                                 # learned within a few layers, and it stays
    noisy = _run(30, PathLaw(filter_mm=7.0), noise=0.1)
    assert max(noisy[10:]) < 0.9                                 # 0.1 mm of sensor noise a bin: bounded


def test_the_factors_keep_the_layers_metal_and_their_bound():
    xy = np.c_[np.arange(0.0, 50.0, 5.0), np.zeros(10)]
    d = Field(xy, np.where(xy[:, 0] > 25, 2.0, -2.0))
    m, need = plan_factors(xy, np.full(10, 5.0), d, None, None, 0.7, PathLaw(bounds=(0.75, 1.25), max_step=2.0))
    assert need.max() > 1.25 and m.max() == pytest.approx(1.25)
    assert m.min() >= 0.75
    assert float(np.mean(1.0 / need)) == pytest.approx(1.0)
    # one layer's reading moves a factor by at most `max_step` (a noisy bin does not throw it to a bound)
    m, need = plan_factors(xy, np.full(10, 5.0), d, None, None, 0.7, PathLaw(bounds=(0.75, 1.25), max_step=0.1))
    assert need.max() > 1.25 and m.max() < 1.15 and m.min() > 0.85


def test_one_stretch_far_out_does_not_push_the_others_to_the_bound():
    # a wall's end that needs 0.3 x the speed: the rest keeps the layer's metal without it
    w = np.full(10, 5.0)
    m = bounded_metal(np.r_[0.3, np.ones(9)], w, 0.6, 1.4)
    assert m[0] == pytest.approx(0.6)
    assert np.all(m[1:] < 1.15)
    assert float(np.sum(w / m)) == pytest.approx(float(w.sum()))


def test_samples_of_one_report_spread_over_the_move_to_the_next():
    # the robot reported reaching 0, then 3.5 (three samples each), then 7 (two, the pass ends at 8)
    got = spread_reports([(0.0, 1.0)] * 3 + [(3.5, 2.0)] * 3 + [(7.0, 3.0)] * 2, 8.0)
    assert [round(s, 3) for s, _ in got] == [0.583, 1.75, 2.917, 4.083, 5.25, 6.417, 7.25, 7.75]
    assert [v for _, v in got] == [1.0] * 3 + [2.0] * 3 + [3.0] * 2


def test_the_rise_is_set_by_speed_and_wire_feed_keeping_the_beads_width():
    v0, f0 = np.full(4, 940.0), np.full(4, 6.0)
    rise = np.array([0.9, 1.0, 1.2, 1.4])
    wide = (np.full(4, 100.0), np.full(4, 3000.0)), (np.full(4, 4.0), np.full(4, 7.4))
    v, f = process_for(rise, v0, f0, LAW, *wide)
    assert np.allclose(rise_ratio(LAW, v, f, v0, f0), rise, rtol=1e-4)       # the rise asked
    assert np.allclose(LAW.width(f, v), LAW.width(f0, v0), rtol=1e-3)       # at the planned width
    assert np.all(np.diff(v) < 0) and np.all(np.diff(f) < 0)                # more metal: slower, less wire
    assert v[1] == pytest.approx(940.0) and f[1] == pytest.approx(6.0)
    # the wire feed at its bound: the speed alone takes the rest (the bead narrows), then its own bound
    v, f = process_for(np.array([0.6, 0.5]), v0[:2], f0[:2], LAW, (np.full(2, 100.0), np.array([3000.0, 1200.0])),
                       (np.full(2, 4.0), np.full(2, 6.3)))
    assert np.allclose(f, 6.3) and rise_ratio(LAW, v[:1], f[:1], v0[:1], f0[:1])[0] == pytest.approx(0.6, rel=1e-4)
    assert v[1] == pytest.approx(1200.0) and LAW.width(f[:1], v[:1])[0] < LAW.width(f0[:1], v0[:1])[0]

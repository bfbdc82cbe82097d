"""A hidden region's edge along a pass (controller/runtime/path_edges.py, docs/closed-loop.md
"Region edges"): found in noisy raw tops finer than the bins, kept from layer to layer, and the pass
split there so no segment lays one process over both gains."""
from __future__ import annotations

import numpy as np

from controller.runtime.path_edges import EdgeFinder, best_steps
from controller.runtime.path_plan import Field, arc_length, bin_samples, cut_polyline, resample

EDGE = 23.25


def test_a_step_is_found_between_the_samples_and_noise_alone_is_not():
    rng = np.random.default_rng(3)
    s = rng.uniform(0.0, 60.0, 400)
    g = 1.0 + 0.47 * (s > EDGE) + 0.2 * rng.standard_normal(len(s))
    got = best_steps(s, g, 10.0, 50.0, 7.0, 4.5, 0.3)
    assert len(got) == 1 and abs(got[0][0] - EDGE) < 0.3 and 0.35 < got[0][1] < 0.6
    assert best_steps(s, 1.0 + 0.2 * rng.standard_normal(len(s)), 10.0, 50.0, 7.0, 4.5, 0.3) == []


def test_the_pass_is_split_at_the_edge_and_neither_the_field_nor_a_bin_reaches_across():
    pts, idx = resample(np.array([[-46.5, 0.0, 1.0], [46.5, 0.0, 1.0]]), 3.5)
    cut = np.array([[EDGE, 0.0, 1.0, 0.0]])
    out, ix = cut_polyline(pts, idx, cut)
    assert len(out) == len(pts) + 1 and np.any(np.isclose(out[:, 0], EDGE))
    assert np.all(np.diff(ix) > 0)   # the new point's index lies between its neighbours'
    xy = np.column_stack([np.arange(15.0, 32.0, 0.5), np.zeros(34)])
    f = Field(xy, np.where(xy[:, 0] > EDGE, 2.0, -2.0))
    near = np.array([[EDGE - 0.3, 0.0], [EDGE + 0.3, 0.0]])
    assert np.allclose(f.at(near, 1.75, 7.0, cut), [-2.0, 2.0])
    assert abs(f.at(near, 1.75, 7.0)[0]) < 1.0     # without the cut the kernel mixes both sides
    samples = [(s, 1.0 if s < 40.0 else 3.0) for s in np.arange(35.0, 45.0, 0.25)]
    bins = bin_samples(samples, 93.0, 10.0, breaks=[40.0])
    assert all(v in (1.0, 3.0) for _s, v, _n in bins)


def test_the_finder_takes_an_edge_seen_two_layers_running_and_keeps_it():
    rng = np.random.default_rng(5)
    pts = np.array([[-46.5, 0.0, 0.0], [46.5, 0.0, 0.0]])
    cum = arc_length(pts)
    ef = EdgeFinder(width_mm=7.0)
    top = np.zeros(600)
    s = np.linspace(3.5, 93.0, 600)
    gain = np.where(pts[0, 0] + s > EDGE, 1.25, 0.85)
    found = []
    for la in range(12):
        top = top + 0.77 * gain
        ef.add(la, 0, pts, cum, list(zip(s, top + 0.7 * rng.standard_normal(len(s)))), np.ones(1))
        found.append(ef.find(la).copy())
    assert all(len(c) == 0 for c in found[:2])
    last = found[-1]
    assert len(last) == 1 and abs(last[0, 0] - EDGE) < 0.5
    assert sum(len(c) == 1 for c in found) >= 8

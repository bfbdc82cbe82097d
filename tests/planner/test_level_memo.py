"""A layer the feed-forward levelled before is reused for a later layer of the same inputs
(planner/level_memo.py): the job is the same byte for byte as levelling every layer."""
from __future__ import annotations

import dataclasses
import pickle
from typing import Any, Callable

import numpy as np

from planner import level_memo
from planner.ahead import Done, Later
from planner.feedforward import Envelope, level_layer
from planner.job import Pass

ENV = Envelope(30.0, 6000.0, 2.0, 12.0)


def _layer(z: float) -> tuple[Pass, ...]:
    """Two loops of a ring crowding at one side (their spread levelled) and a bead along the middle."""
    t = np.linspace(0.0, 2 * np.pi, 60)
    outer = np.column_stack([20 * np.cos(t), 20 * np.sin(t), np.full(60, z)])
    inner = np.column_stack([3 + 15 * np.cos(t), 15 * np.sin(t), np.full(60, z)])
    line = np.column_stack([np.linspace(-5, 5, 6), np.zeros(6), np.full(6, z)])
    nrm = np.column_stack([np.cos(t), np.sin(t), np.zeros(60)])
    return (Pass("perimeter", 6.0, 180.0, 400.0, 6.0, outer, nrm),
            Pass("perimeter", 6.0, 180.0, 400.0, 6.0, inner),
            Pass("infill", 6.0, 180.0, 420.0, 6.0, line))


def _here(fn: Callable[..., level_memo.Levelled], *args: Any) -> Done[level_memo.Levelled]:
    return Done(fn(*args))


def _same(a: tuple[Pass, ...], b: tuple[Pass, ...]) -> bool:
    def fields(p: Pass) -> list[object]:
        return [v.tobytes() if isinstance(v, np.ndarray) else v for v in dataclasses.astuple(p)]
    return len(a) == len(b) and all(fields(x) == fields(y) for x, y in zip(a, b))


def test_a_layer_of_the_same_passes_at_another_height_gets_what_levelling_it_gives():
    memo = level_memo.LevelMemo()
    first = memo.level(_here, _layer(1.5), 1.0, ENV).result()
    again = memo.level(_here, _layer(3.0), 1.0, ENV)
    assert memo.hits == 1
    out, lvl = again.result()
    want, want_lvl = level_layer(_layer(3.0), 1.0, ENV)
    assert want_lvl.passes_levelled > 0 and lvl == want_lvl and first[1] == want_lvl
    assert _same(out, want)
    assert {float(z) for p in out for z in p.points[:, 2]} == {3.0}


def test_a_layer_levelled_on_a_worker_process_is_reused_from_its_copy():
    """A worker's result comes back pickled (no pass is the one sent): every pass gets the new height."""
    memo = level_memo.LevelMemo()
    memo.level(lambda fn, *a: Done(pickle.loads(pickle.dumps(fn(*a)))), _layer(1.5), 1.0, ENV).result()
    out, _ = memo.level(_here, _layer(4.5), 1.0, ENV).result()
    assert _same(out, level_layer(_layer(4.5), 1.0, ENV)[0])


def test_other_speeds_or_wire_are_levelled_anew_other_normals_are_not():
    """The feed-forward levels by the points, speeds and wire feeds, and carries the boundary
    normals along: a layer whose normals alone differ gets the levelled speeds and its own normals."""
    memo = level_memo.LevelMemo()
    memo.level(_here, _layer(1.5), 1.0, ENV)
    slower = tuple(dataclasses.replace(p, speed_mm_min=390.0) for p in _layer(3.0))
    memo.level(_here, slower, 1.0, ENV)
    memo.level(_here, _layer(3.0), 1.2, ENV)   # another wire
    assert memo.hits == 0
    turned = (dataclasses.replace(_layer(3.0)[0], normals=-_layer(3.0)[0].normals),) + _layer(3.0)[1:]
    out, _ = memo.level(_here, turned, 1.0, ENV).result()
    assert memo.hits == 1
    assert _same(out, level_layer(turned, 1.0, ENV)[0])
    assert out[0].normals is not None and np.all(np.sum(out[0].normals[:, :2] * out[0].points[:, :2], axis=1) < 0)


def test_a_prism_plans_the_same_job_with_the_memo_as_levelling_every_layer(monkeypatch):
    import trimesh  # the test's part

    from core.config import load_material
    from planner.job import job_to_json
    from planner.plan import PlanOptions, plan_part

    mesh = trimesh.creation.cylinder(radius=12.0, height=40.0, sections=6)   # a hexagonal prism: its corners take either facet's normal
    opts = PlanOptions(width_mm=6.0, allow_underfill=True, allow_overhang=True)
    mat = load_material("inconel718-1.0mm")
    hits: list[int] = []
    real = level_memo.LevelMemo.level

    def counted(self: level_memo.LevelMemo, submit: level_memo.Submit, passes: tuple[Pass, ...], wire: float,
                env: Envelope) -> Later[level_memo.Levelled]:
        out = real(self, submit, passes, wire, env)
        hits.append(self.hits)
        return out

    monkeypatch.setattr(level_memo.LevelMemo, "level", counted)
    memo_job = job_to_json(plan_part(mesh, opts, mat))
    monkeypatch.setattr(level_memo, "layer_key", lambda *a: None)
    every_job = job_to_json(plan_part(mesh, opts, mat))
    assert max(hits) > 0
    assert len(memo_job) > 10_000 and memo_job == every_job

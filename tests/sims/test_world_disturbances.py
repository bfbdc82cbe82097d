"""The simulated world's hidden disturbances along the path (issue 35, docs/process-physics.md):
regions with their own gains, a bead start's run-in, an open end's sag. Judged on the world's own
height map and deposit.jsonl; set in sim.yaml, validated like every other key."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.config import ProcessSim, SimRegion, load_material, load_sim
from core.errors import ConfigError
from planner.process import inverse
from sims.process_world import ProcessPhysics
from sims.world import World

MAT = load_material("inconel718-1.0mm")
PP = inverse(MAT, 7.0)


def _bead(w: World, path: list[tuple[float, float]], z: float, t: float, step: float = 2.0) -> float:
    """One bead along a polyline at height z (moves of `step` mm), arc on the whole way; the time after."""
    w.set_arc(True, 127.5, 20.0, t, PP.wfs_m_min)
    k = 0
    for (x0, y0), (x1, y1) in zip(path, path[1:]):
        n = max(1, int(round(np.hypot(x1 - x0, y1 - y0) / step)))
        for i in range(n):
            a, b = i / n, (i + 1) / n
            p0 = (x0 + (x1 - x0) * a, y0 + (y1 - y0) * a, z)
            p1 = (x0 + (x1 - x0) * b, y0 + (y1 - y0) * b, z)
            dt = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1])) / PP.speed_mm_min * 60.0
            w.torch_moved("robot", k, p0, p1, t, t + dt)
            w.motion_stopped("robot")
            t, k = t + dt, k + 1
    w.set_arc(False, 0.0, 0.0, t)
    return t


def _world(log: Path | None = None, defer: bool = False, **process: object) -> World:
    w = World(log_dir=log, defer_lays=defer)
    w.use_physics(ProcessPhysics(MAT, ProcessSim.model_validate(process)))
    return w


def _top(w: World, x: float, y: float = 0.1) -> float:
    assert w.physics is not None
    return w.physics.maps["robot"].surface(x, y)


def _wire_mm3(length: float) -> float:
    return float(np.pi * MAT.wire_diameter_mm ** 2 / 4 * PP.wfs_m_min * 1000.0 / PP.speed_mm_min * length)


def test_a_region_lays_with_its_own_gain_and_the_deposit_log_shows_it(tmp_path: Path):
    # (60 mm: a bead's first and last pool, two bead widths each, lie at 0-12 and 48-60 mm)
    w = _world(tmp_path, regions=(SimRegion(box_mm=(20.0, -10.0, 80.0, 10.0), height_gain=1.25),))
    _bead(w, [(0.0, 0.0), (60.0, 0.0)], PP.height_mm, 0.0)
    w.flush()
    outside, inside = _top(w, 16.1), _top(w, 30.1)
    assert inside / outside == pytest.approx(1.25, rel=0.03)      # the region's hidden gain, not the global one
    rows = [json.loads(s) for s in (tmp_path / "deposit.jsonl").read_text().splitlines()]
    h = {round(r["from"][0]): r["bead_height_mm"] for r in rows}
    # (a row's bead height is the rise half a bead width and a cell behind the row's end: rows
    # 16 -> 18 mm and 36 -> 38 mm read it at 14.5 and 34.5 mm)
    assert h[36] / h[16] == pytest.approx(1.25, rel=0.05)
    # a segment straddling the box's edge is cut there: the step lies at x = 20, not at a move's end
    w2 = _world(regions=(SimRegion(box_mm=(21.0, -10.0, 80.0, 10.0), height_gain=1.25),))
    _bead(w2, [(0.0, 0.0), (60.0, 0.0)], PP.height_mm, 0.0)
    assert _top(w2, 16.6) == pytest.approx(outside, rel=0.01)
    assert _top(w2, 24.6) == pytest.approx(inside, rel=0.01)
    assert _top(w2, 20.6) == pytest.approx(outside, rel=0.01)      # the move 20 -> 22 mm steps at 21
    assert _top(w2, 21.1) == pytest.approx(inside, rel=0.01)


def test_a_bead_start_runs_in_thin_and_the_metal_it_misses_is_a_quarter_of_the_run_in():
    ref, w = _world(), _world(start_run_in_mm=8.0)
    for x in (ref, w):
        _bead(x, [(0.0, 0.0), (40.0, 0.0)], PP.height_mm, 0.0)
    assert ref.physics is not None and w.physics is not None
    # half the metal at the start, linearly to all at 8 mm: 8/4 mm of bead missing
    missing = ref.physics.maps["robot"].volume_mm3 - w.physics.maps["robot"].volume_mm3
    assert missing == pytest.approx(_wire_mm3(2.0), rel=0.05)
    ratio = [_top(w, x + 0.1) / _top(ref, x + 0.1) for x in range(0, 8)]
    # every mm of the run-in thinner: the bead's first pool (two bead widths, 12 mm, and its round
    # start) levels the metal it misses out over itself
    assert max(ratio) < 0.98 and 0.8 < float(np.mean(ratio)) < 0.95
    assert _top(w, 20.1) == pytest.approx(_top(ref, 20.1), abs=1e-9)  # nominal past it


def _wall(w: World, layers: int) -> None:
    t = 0.0
    for la in range(layers):
        a, b = (0.0, 40.0) if la % 2 == 0 else (40.0, 0.0)
        t = _bead(w, [(a, 0.0), (b, 0.0)], (la + 1) * PP.height_mm, t + 1.0)


@pytest.mark.parametrize("defer", [False, True])
def test_an_open_end_sags_and_a_closed_loop_does_not(defer: bool):
    ref, w = _world(), _world(defer=defer, end_sag=0.3)
    _wall(ref, 4)
    _wall(w, 4)
    w.settle()
    assert ref.physics is not None and w.physics is not None
    # the last bead ran 0 -> 40 mm... and back: layer 3 ends at x = 0, its last width sags
    end, mid = _top(w, 3.1) - _top(ref, 3.1), _top(w, 20.1) - _top(ref, 20.1)
    assert end < -0.05
    assert abs(mid) < 0.01                                            # the middle keeps its metal
    lost = ref.physics.maps["robot"].volume_mm3 - w.physics.maps["robot"].volume_mm3
    assert 0.3 * _wire_mm3(7.0) * 0.8 * 4 < lost < 0.3 * _wire_mm3(7.0) * 1.6 * 4   # every layer, its last width
    ring = [(0.0, 0.0), (30.0, 0.0), (30.0, 30.0), (0.0, 30.0), (0.0, 0.0), (6.0, 0.0)]
    r0, r1 = _world(), _world(defer=defer, end_sag=0.3)
    for x in (r0, r1):
        _bead(x, ring, PP.height_mm, 0.0)
        x.settle()
    assert r0.physics is not None and r1.physics is not None
    assert r1.physics.maps["robot"].volume_mm3 == pytest.approx(r0.physics.maps["robot"].volume_mm3, rel=1e-9)


def test_sim_yaml_disturbances_are_validated_naming_the_file_and_key(tmp_path: Path):
    good = tmp_path / "sim.yaml"
    good.write_text("process:\n  regions:\n    - {box_mm: [0, 0, 10, 20], height_gain: 1.25}\n"
                    "  start_run_in_mm: 5\n  end_sag: 0.2\n")
    cfg = load_sim(good)
    assert cfg.process.regions[0].height_gain == 1.25 and cfg.process.end_sag == 0.2
    bad = tmp_path / "bad.yaml"
    bad.write_text("process:\n  regions:\n    - {box_mm: [0, 0, 10, 20], gain: 1.25}\n")
    with pytest.raises(ConfigError) as e:
        load_sim(bad)
    assert "bad.yaml" in str(e.value) and "gain" in str(e.value)
    bad.write_text("process:\n  regions:\n    - {box_mm: [10, 0, 0, 20]}\n")
    with pytest.raises(ConfigError, match="x0 < x1"):
        load_sim(bad)
    bad.write_text("process:\n  end_sags: 0.2\n")
    with pytest.raises(ConfigError, match="end_sags"):
        load_sim(bad)

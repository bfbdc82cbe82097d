"""A short bead is welded onto the nearest open bead end (planner/stubs.py): the nearest end is
found over every bead at once, the first of equals in bead order, as a loop over them finds it."""
from __future__ import annotations

import numpy as np
from shapely.geometry import box

from planner.path2d import Path2D
from planner.stubs import no_stubs


def _beads(rng: np.random.Generator) -> list[list[Path2D]]:
    """Open rows at random and a few twins (the same ends, reversed: equal distances), one loop, two stubs."""
    rows = [Path2D("infill", np.array([[x, y], [x + 30.0, y]]), 4.0)
            for x, y in zip(rng.uniform(0, 60, 30), rng.uniform(0, 60, 30))]
    rows += [Path2D("infill", r.points[::-1].copy(), 4.0) for r in rows[:3]]   # the same ends again
    loop = Path2D("perimeter", np.array([[0.0, 0.0], [90.0, 0.0], [90.0, 90.0], [0.0, 90.0], [0.0, 0.0]]), 4.0, True)
    stubs = [Path2D("gap", np.array([[x, y], [x + 1.5, y + 0.5]]), 4.0) for x, y in rng.uniform(5, 85, (2, 2))]
    return [[loop], rows, stubs]


def _nearest_by_loop(stub: Path2D, groups: list[list[Path2D]], reach: float) -> tuple[int, int] | None:
    best = None
    for gi, g in enumerate(groups):
        for qi, q in enumerate(g):
            if q.closed:
                continue
            for q_end in (0, -1):
                for s_end in (0, -1):
                    d = float(np.hypot(*(q.points[q_end] - stub.points[s_end])))
                    if d <= reach and (best is None or d < best[0]):
                        best = (d, gi, qi)
    return None if best is None else (best[1], best[2])


def test_a_stub_goes_to_the_bead_a_loop_over_the_ends_finds():
    island = box(-10, -10, 100, 100)
    picked = set()
    for seed in range(12):
        groups = _beads(np.random.default_rng(seed))
        stub = groups[2][0]
        want = _nearest_by_loop(stub, [groups[0], groups[1], []], 12.0)
        out = no_stubs([groups[0], groups[1], [stub]], 8.0, island, 0, [], 12.0)
        grown = [(1, qi) for qi, q in enumerate(out[1]) if len(q.points) > 2]   # a row the stub was welded onto
        assert grown == ([want] if want is not None else []), seed
        picked.add(want)
    assert len(picked - {None}) > 3   # several rows: the twins among them

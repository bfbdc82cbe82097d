"""A bead laid over a part's free edge (docs/process-physics.md "Free edges"): the pool hangs on
the side face; it is not lost down it, the first bead slumps there, the next stand on it."""
from __future__ import annotations

import numpy as np

from sims.heightmap import FloatArray, HeightMap


def _half_plate(xs: FloatArray, ys: FloatArray) -> FloatArray:
    """A plate whose top z = 0 ends at x = 0 (nothing under x > 0)."""
    return np.where(np.asarray(xs) < 0.0, 0.0, np.nan)


def _layers(x: float, n: int, substrate: object = None) -> list[float]:
    """Lay n beads (4 mm wide, 4 mm² each) along y at x, one on the other; the top 0.25 mm inside
    the edge after each."""
    hm = HeightMap(0.5, _half_plate) if substrate is None else HeightMap(0.5)
    tops = []
    for _ in range(n):
        hm.new_bead()
        laid = hm.lay((x, -20.0), (x, 20.0), 4.0, 4.0)
        assert laid.lost_mm3 < 1e-3   # float rounding only
        tops.append(float(hm.deposit_tops(np.array([-0.25]), np.array([0.0]))[0]))
    return tops


def test_a_bead_half_over_the_edge_keeps_its_metal_and_slumps_there() -> None:
    edge = _layers(0.0, 1)[0]
    plate = _layers(0.0, 1, substrate="flat")[0]
    # the hanging half took its share first: lower at the edge than on a plate, but metal is there
    assert 0.05 < edge < 0.8 * plate
    hm = HeightMap(0.5, _half_plate)
    hm.new_bead()
    hm.lay((0.0, -20.0), (0.0, 20.0), 4.0, 4.0)
    # the lip over the edge is metal with air under it: the map's top, 1.5·area/w below the base at most
    lip = hm.deposit_tops(np.array([0.75, 1.75]), np.array([0.0, 0.0]))
    assert np.all(np.isfinite(lip)) and np.all(lip >= -1.5 - 1e-9)


def test_beads_laid_on_the_slumped_one_stand_as_on_a_plate() -> None:
    tops = np.array(_layers(0.0, 4))
    plate = np.array(_layers(0.0, 3, substrate="flat"))
    # over the slumped first bead the next three stand as the first three of a stack on a plate:
    # the edge is one slumped layer behind, no more (the deficit a repair's stock probe finds)
    assert np.allclose(tops[1:] - tops[0], plate, atol=0.05), (tops, plate)

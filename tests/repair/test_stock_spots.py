"""The stock probe's spots (issue 36): dense where a deposit falls short first, the repaired region's
corners and along its boundary, then a grid over its inside (docs/machining.md "The stock probe")."""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from controller.align.surface_probe import refine_spots, stock_spots
from controller.job.repair_volume import to_manifold, to_trimesh


def _block_with(cuts: list[tuple[tuple[float, float, float], tuple[float, float, float]]]):
    cad = trimesh.creation.box(extents=(100, 100, 20))
    cad.apply_translation((0, 0, -10))
    stock = to_manifold(cad, "cad")
    for k, (ext, ctr) in enumerate(cuts):
        b = trimesh.creation.box(extents=ext)
        b.apply_translation(ctr)
        stock = stock - to_manifold(b, f"cut{k}")
    return np.asarray(cad.triangles), np.asarray(to_trimesh(stock).triangles)


def test_a_pocket_is_probed_at_its_corners_first_along_its_walls_and_inside():
    cad, stock = _block_with([((20, 20, 4), (40, 40, -2))])
    xy, kinds = stock_spots(cad, stock, np.array([[30.0, 30.0], [50.0, 50.0]]))
    corners = {(30.25, 30.25), (49.75, 30.25), (30.25, 49.75), (49.75, 49.75)}
    assert {tuple(p) for p in xy[:4].round(2).tolist()} == corners and kinds[:4] == ["corner"] * 4
    assert set(kinds) == {"corner", "ring", "inside"}
    # no cell of the region farther than the inside spacing (2 mm) from a spot; within 0.6 mm of every cell along the walls
    g = np.arange(30.25, 50.0, 0.5)
    cells = np.array([(x, y) for x in g for y in g])
    d = cKDTree(xy).query(cells)[0]
    assert d.max() <= 2.0, d.max()
    wall = cells[np.min(np.column_stack([cells - 30, 50 - cells]), axis=1) <= 1.0]
    assert cKDTree(xy).query(wall)[0].max() <= 0.6
    assert 180 <= len(xy) <= 240                     # every boundary cell, 2 mm inside, not every cell


def test_an_l_gets_its_inner_corner_and_leg_ends():
    cad, stock = _block_with([((30, 8, 4), (-25, -36, -2)), ((8, 30, 4), (-36, -25, -2))])
    xy, kinds = stock_spots(cad, stock, np.array([[-40.0, -40.0], [-10.0, -10.0]]))
    near = cKDTree(xy)
    for leg_end in ((-10.25, -39.75), (-10.25, -32.25), (-39.75, -10.25), (-32.25, -10.25), (-39.75, -39.75)):
        assert near.query(leg_end)[0] <= 0.01, leg_end      # each outer corner is a spot
    assert near.query((-31.75, -31.75))[0] <= 1.0            # and the inner corner (concave) has one near


def test_low_touches_are_refined_around_within_the_region_only():
    cad, stock = _block_with([((20, 20, 4), (40, 40, -2))])
    rb = np.array([[30.0, 30.0], [52.0, 52.0]])       # the repair hangs 2 mm over the free edges
    xy, _ = stock_spots(cad, stock, rb)
    k = int(np.argmin(np.hypot(*(xy - 40.0).T)))
    low = np.zeros(len(xy), dtype=bool)
    low[k] = True                                      # a touch in the middle stands short
    more = refine_spots(cad, stock, rb, xy, low, 1.0)
    assert len(more) >= 6
    # around that touch only, at 1 mm from every touch and from each other, never off the part
    assert np.max(np.hypot(*(more - xy[k]).T)) <= 2.0 + 1e-9
    assert cKDTree(xy).query(more)[0].min() >= 1.0 - 1e-9
    assert np.all((more >= 30.0) & (more <= 50.0))
    if len(more) > 1:
        d = np.hypot(*(more[:, None, :] - more[None, :, :]).transpose(2, 0, 1))
        assert d[~np.eye(len(more), dtype=bool)].min() >= 1.0 - 1e-9
    assert not len(refine_spots(cad, stock, rb, xy, np.zeros(len(xy), dtype=bool), 1.0))

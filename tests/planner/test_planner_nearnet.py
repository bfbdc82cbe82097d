"""Near-net planning (issue 28 item 1, docs/contract.md §3.9): --machining-allowance grows every layer
and the top; coverage, outside and mass balance against the grown region; stock per face; the
refused features an allowance would make buildable."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
import trimesh
from shapely.geometry import box

from core.config import load_material
from core.errors import InputError, MeshError
from planner.extrude import extrude
from planner.nearnet import allowance_for, grow
from planner.plan import PlanOptions, plan_part
from planner.thin import legal_widths

MAT = load_material("inconel718-1.0mm")
WIRE = np.pi * MAT.wire_diameter_mm ** 2 / 4
RIB = extrude(box(0, 0, 80, 3.0), 10.0)  # a 3 mm rib: narrower than the smallest legal bead (4.47 mm)


def test_a_rib_too_thin_for_a_bead_is_refused_naming_the_allowance_that_builds_it():
    with pytest.raises(MeshError) as err:
        plan_part(RIB, PlanOptions(width_mm=6.0), MAT)
    msg = str(err.value)
    assert "3.00 mm wide" in msg and "buildable with --machining-allowance 0.75 mm" in msg
    assert "--machining-allowance 0.75 would make 15 of the" in msg


def test_the_allowance_builds_it_oversize_and_carries_the_stock_per_face():
    job = plan_part(RIB, PlanOptions(width_mm=6.0, machining_allowance_mm=1.5), MAT)
    h = job.layers[0].height_mm
    grown = box(0, 0, 80, 3.0).buffer(1.5, quad_segs=8)
    for layer in job.layers:
        fp = shapely.union_all([shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2)
                                for p in layer.passes])
        assert fp.intersection(grown).area / grown.area >= 0.97
        assert fp.difference(grown).area / fp.area <= 0.03
        laid = sum(WIRE * p.wfs_m_min * 1000 / p.speed_mm_min * p.length_mm for p in layer.passes)
        assert laid == pytest.approx(grown.area * h, rel=0.03)
        assert fp.contains(box(0, 0, 80, 3.0))  # the net part is inside the deposit
    m = job.summary["machining"]
    assert m["allowance_mm"] == 1.5
    assert len(job.layers) * h >= 10.0 + 1.5 and m["stock_mm"]["top"] >= 1.5
    assert m["top_layers_added"] == len(job.layers) - 15
    assert 0.0 < m["stock_mm"]["side_min"] <= 1.5 <= m["stock_mm"]["side_max"] + 1e-3
    assert m["stock_mm"]["bottom"] == 0.0


def test_the_material_default_applies_and_the_option_overrides_it():
    mat = MAT.model_copy(update={"machining_allowance_mm": 1.0})
    job = plan_part(RIB, PlanOptions(width_mm=6.0), mat)
    assert job.summary["machining"]["allowance_mm"] == 1.0
    assert plan_part(extrude(box(0, 0, 40, 20), 2.0), PlanOptions(width_mm=6.0, machining_allowance_mm=0.0),
                     mat).summary["machining"] == {"allowance_mm": 0.0}
    with pytest.raises(InputError, match="machining-allowance"):
        PlanOptions(width_mm=6.0, machining_allowance_mm=-1.0)


def test_grow_and_allowance_for():
    assert grow([box(0, 0, 10, 10)], 1.0)[0].area == pytest.approx(144 - 4 + np.pi, rel=1e-3)
    assert len(grow([box(0, 0, 10, 10), box(11, 0, 20, 10)], 1.0)) == 1  # islands 1 mm apart merge
    wd = legal_widths(MAT, 0.66, 6.0, 0.738, False)
    assert allowance_for(3.0, wd, 12.0) == pytest.approx(0.75)  # 3 + 2·0.75 = 4.5 ≥ 4.47
    assert allowance_for(5.0, wd, 12.0) == 0.0
    assert allowance_for(7.0, wd, 12.0) > 0.0  # between one widest and two narrowest beads


def _covered(job, grown_of) -> list[float]:
    """Share of each layer's grown region (grown_of(layer)) the beads' footprint covers."""
    out = []
    for layer in job.layers:
        fp = shapely.union_all([shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2)
                                for p in layer.passes])
        g = grown_of(layer)
        out.append(fp.intersection(g).area / g.area)
    return out


def test_a_fin_narrower_than_a_bead_even_grown_is_built_standing_out_into_its_stock():
    """Issue 40: a 0.3 mm fin 4 mm beside a block (the octagonal pocket's edge) is 3.3 mm wide grown
    by 1.5 mm, narrower than the smallest legal bead at 8 mm (5.46 mm): the bead may stand out of the
    grown region by at most the allowance (stock up to 2a there). On this small block that puts 4.8 %
    of the deposit out of the grown region (over 1.5 %): refused, naming the fin and the allowance that
    builds it inside the grown region; --allow-underfill builds it standing out."""
    fin = box(0, 0, 0.3, 80)
    part = trimesh.util.concatenate([extrude(fin, 6.0), extrude(box(4.3, 0, 40, 80), 6.0)])
    with pytest.raises(MeshError) as err:
        plan_part(part, PlanOptions(width_mm=8.0, machining_allowance_mm=1.5), MAT)
    assert ("3.33 mm wide in the grown region, narrower than the smallest legal bead (5.46 mm): built 5.48 mm wide, "
            "standing out of it (buildable with --machining-allowance 2.60 mm)") in str(err.value)
    assert "the deposit would stand 4.8 % out of its grown region, over 1.5 %" in str(err.value)
    job = plan_part(part, PlanOptions(width_mm=8.0, machining_allowance_mm=1.5, allow_underfill=True), MAT)
    for layer in job.layers:
        fp = shapely.union_all([shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2)
                                for p in layer.passes])
        assert fp.buffer(1e-6).contains(fin)  # the net fin is inside the deposit
        assert fp.difference(fin.buffer(3.0 + 1e-3)).intersection(box(-10, -10, 2.0, 90)).area < 1.0  # within 2a
    grown = shapely.union_all([fin, box(4.3, 0, 40, 80)]).buffer(1.5, quad_segs=8)
    assert min(_covered(job, lambda L: grown)) >= 0.97


def test_a_pad_too_small_for_a_bead_of_the_minimum_length_gets_one_loop_into_its_stock():
    """A 7 x 5 mm pad (the riser's feet) at 8 mm beads: no bead of 16 mm fits in it grown by 1.5 mm;
    one closed loop standing out of it by at most the allowance covers it. Beside this small block the
    loop puts 5.1 % of the deposit out of the grown region (over 1.5 %): refused, named;
    --allow-underfill builds it."""
    pad = box(0, 0, 7, 5)
    part = trimesh.util.concatenate([extrude(pad, 4.0), extrude(box(20, 0, 60, 20), 4.0)])
    with pytest.raises(MeshError, match="10.00 x 8.00 mm grown, gets no bead of at least 16.0 mm inside the grown "
                                        "region: built as one loop standing out of it"):
        plan_part(part, PlanOptions(width_mm=8.0, machining_allowance_mm=1.5), MAT)
    job = plan_part(part, PlanOptions(width_mm=8.0, machining_allowance_mm=1.5, allow_underfill=True), MAT)
    for layer in job.layers:
        on_pad = [p for p in layer.passes if p.points[:, 0].max() < 15.0]
        assert len(on_pad) == 1 and on_pad[0].length_mm >= 16.0
        fp = shapely.buffer(shapely.linestrings(on_pad[0].points[:, :2]), on_pad[0].width_mm / 2)
        assert fp.contains(pad) and pad.buffer(3.0).contains(fp)
    with pytest.raises(MeshError, match="gets no bead of at least 16.0 mm"):
        plan_part(part, PlanOptions(width_mm=8.0), MAT)


def test_the_region_is_grown_in_3d_so_a_small_step_out_is_no_overhang():
    """A block whose upper part steps out 0.6 mm (beyond the 0.38 mm rule at 0.66 mm layers): net, an
    overhang; near-net, the stock under the step belongs to the layers below it (the part grown by
    the allowance in 3-D), so nothing steps out beyond the rule."""
    part = trimesh.util.concatenate([extrude(box(0, 0, 40, 20), 3.3), extrude(box(0, 0, 40.6, 20), 3.3, z0=3.3)])
    with pytest.raises(MeshError, match="overhang rule"):
        plan_part(part, PlanOptions(width_mm=6.0), MAT)
    job = plan_part(part, PlanOptions(width_mm=6.0, machining_allowance_mm=1.5), MAT)
    assert job.summary["overhang_layers"] == []
    h = job.layers[0].height_mm
    first_up = round(3.3 / h)  # the first layer of the wider part; the layer under it holds its stock
    reach = max(p.points[:, 0].max() + p.width_mm / 2 for p in job.layers[first_up - 1].passes)
    assert reach >= 40.6 + np.sqrt(1.5 ** 2 - h ** 2) - 0.2


def test_a_refusal_in_the_grown_region_names_the_allowance_that_builds_it():
    """A free-standing 0.3 mm fin at 8 mm beads with 0.5 mm of allowance: 1.3 mm grown, 2.3 mm with the
    bead standing out 0.5 mm a side, still narrower than 5.46 mm: refused, naming the allowance at
    which it is built inside the grown region (0.3 + 2a >= 5.46: 2.60 mm); planned at that allowance.
    At 1.30 mm (built standing out 1.3 mm a side, 48 % of the deposit outside the grown region) it is
    refused naming the same."""
    fin = extrude(box(0, 0, 0.3, 80), 4.0)
    with pytest.raises(MeshError) as err:
        plan_part(fin, PlanOptions(width_mm=8.0, machining_allowance_mm=0.5), MAT)
    assert "narrower than the smallest legal bead (5.46 mm) (buildable with --machining-allowance 2.60 mm)" in str(err.value)
    with pytest.raises(MeshError, match="standing out of it \\(buildable with --machining-allowance 2.60 mm\\)"):
        plan_part(fin, PlanOptions(width_mm=8.0, machining_allowance_mm=1.3), MAT)
    job = plan_part(fin, PlanOptions(width_mm=8.0, machining_allowance_mm=2.6), MAT)
    assert job.summary["underfill_features"] == 0


def _bored_block(bore_d: float = 5.0) -> trimesh.Trimesh:
    """A 40 x 20 x 12 mm block with a horizontal bore along y, its axis 6 mm up (the roof of a bore
    is an overhang at every layer above its widest)."""
    prof = box(0, 0, 40, 12).difference(shapely.Point(20, 6).buffer(bore_d / 2, quad_segs=24))
    m = extrude(prof, 20.0)
    m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    m.apply_translation(-m.bounds[0])
    return m


def test_the_stock_under_a_narrowed_bore_is_filled_so_its_roof_is_no_overhang():
    """A 5 mm bore: net, its roof overhangs (refused); near-net, the allowance narrows it to a 2 mm slot
    whose roof still overhangs the grown region, so the stock under it is filled from the top down
    (a layer steps out at most the rule's step over the one below) within the allowance, and machined
    away with the rest: planned, nothing beyond the rule, the net part inside the deposit."""
    part = _bored_block()
    with pytest.raises(MeshError, match="overhang rule"):
        plan_part(part, PlanOptions(width_mm=6.0), MAT)
    job = plan_part(part, PlanOptions(width_mm=6.0, machining_allowance_mm=1.5), MAT)
    assert job.summary["overhang_layers"] == []
    net = shapely.box(0, 0, 40, 20)
    for layer in job.layers:
        fp = shapely.union_all([shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2)
                                for p in layer.passes])
        z = (layer.index + 0.5) * layer.height_mm
        d = 2 * np.sqrt(max(2.5 ** 2 - (z - 6.0) ** 2, 0.0))  # the bore's chord at this layer
        part_here = net.difference(shapely.box(20 - d / 2, 0, 20 + d / 2, 20)) if z < 12 else net
        assert fp.intersection(part_here).area >= 0.99 * part_here.area
        assert fp.difference(net.buffer(3.0)).area <= 0.03 * fp.area  # beads stand out at most 2a


def test_an_overhang_beyond_the_allowance_is_still_refused_near_net():
    """A shelf standing out 8 mm over its column: the stock the allowance gives cannot carry it."""
    part = trimesh.util.concatenate([extrude(box(0, 0, 30, 20), 6.0), extrude(box(0, 0, 38, 20), 3.0, z0=6.0)])
    with pytest.raises(MeshError, match="overhang rule"):
        plan_part(part, PlanOptions(width_mm=6.0, machining_allowance_mm=1.5), MAT)


def test_a_wall_one_bead_wide_grown_is_one_bead_run_on_into_its_stock_not_patched():
    """Issue 40: an 80 x 5.2 mm wall at 8 mm beads is 8.2 mm wide grown by 1.5 mm, one widest legal bead
    (8.0 mm) wide. Its bead stopped where the wall's inscribed circle shrinks, leaving the grown ends'
    corners (95.6 % covered), and extra narrow beads patched them standing 14 % out of the grown region.
    Now the one bead runs on into the stock at its ends just until the layer is covered."""
    job = plan_part(extrude(box(0, 0, 80, 5.2), 10.0), PlanOptions(width_mm=8.0, machining_allowance_mm=1.5), MAT)
    grown = box(0, 0, 80, 5.2).buffer(1.5, quad_segs=8)
    for layer in job.layers:
        assert len(layer.passes) == 1
        p = layer.passes[0]
        fp = shapely.buffer(shapely.linestrings(p.points[:, :2]), p.width_mm / 2, quad_segs=8)
        assert fp.intersection(grown).area / grown.area >= 0.97
        assert fp.difference(grown).area / fp.area <= 0.015
        assert fp.contains(box(0, 0, 80, 5.2))


def test_stock_filled_apart_from_a_layer_smaller_than_a_bead_is_not_added():
    """The stock under an overhang is filled (planner.nearnet.supported), but a piece of it standing apart
    from the layer's region and smaller than any bead (the angle block at 4 mm: 0.2-3 mm² islands, each
    then refused as a feature no bead fills) is not: the layer above overhangs there, and that is named."""
    from planner.nearnet import supported

    big, small = box(0, 0, 20, 20), box(20.5, 0, 22, 2)
    layers = [[big], [big, small]]
    assert len(supported(layers, 0.3, 1.5)[0]) == 2  # a 1.3 mm² island of stock beside the block
    kept = supported(layers, 0.3, 1.5, min_area_mm2=5.0)[0]
    assert len(kept) == 1 and kept[0].equals(big)

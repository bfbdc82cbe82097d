"""5-axis deposition (issue 18): tool axes, overhang rule, collisions, and a build on the CNC simulator."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from bench.five_axis import build, figures, plan5
from controller.cli.main import main
from controller.job.read import job_from_dict
from planner.five_axis import FiveAxisOptions, Nozzle, collisions, overhangs, tool_axes
from planner.job import BeadInfo, Job, Layer, Pass, Source, load_job
from bench.parts5 import cone_frustum, tilted_tube

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


@pytest.mark.parametrize("part", ["tube", "frustum"])
def test_three_axis_plan_names_the_overhanging_layers_and_five_axis_brings_them_within(part, tmp_path, capsys):
    mesh = tilted_tube() if part == "tube" else cone_frustum()
    stl = tmp_path / f"{part}.stl"
    mesh.export(stl)
    rc = main(["plan", str(stl), "--width", "3", "--out", str(tmp_path / "j3.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "overhang rule" in err and "layer 1:" in err and "5-axis" in err
    named = {int(n) for n in __import__("re").findall(r"layer (\d+): steps out", err)}
    assert named >= {1, 2, 3}  # the overhanging layers are named
    rc = main(["plan", str(stl), "--width", "3", "--five-axis", "--out", str(tmp_path / "j5.json"), "--json"])
    assert rc == 0, capsys.readouterr().err
    job = load_job(json.loads((tmp_path / "j5.json").read_text()))
    assert job.summary["overhang"]["remaining"] == []
    assert len(job.summary["overhang"]["three_axis_layers"]) == len(job.layers) - 1  # every layer above the first
    tilts = np.degrees(np.arccos(np.vstack([p.axes for L in job.layers for p in L.passes])[:, 2]))
    assert 40.0 < tilts.max() < 46.0  # 45° walls: the build direction is held vertical (down-hand)


def test_tilt_limit_holds_and_leaves_the_overhang_reported():
    mat = __import__("core.config", fromlist=["load_material"]).load_material("inconel718-1.0mm")
    from planner.plan import PlanOptions, plan_part

    from planner.five_axis import OverhangError

    opt = PlanOptions(width_mm=3.0, five_axis=FiveAxisOptions(tilt_limit_deg=20.0))
    with pytest.raises(OverhangError, match=r"layer 1 \(z .*even tilted up to 20°"):
        plan_part(tilted_tube(height=2.0), opt, mat)
    opt = dataclasses.replace(opt, allow_overhang=True)
    job = plan_part(tilted_tube(height=2.0), opt, mat)
    tilts = np.degrees(np.arccos(np.vstack([p.axes for L in job.layers for p in L.passes])[:, 2]))
    assert tilts.max() <= 20.0 + 1e-3
    assert job.summary["overhang"]["remaining"], "a 20° tool cannot bring a 45° wall within a 30° rule"


def _job(layers: list[list[tuple[np.ndarray, np.ndarray | None]]], h: float = 0.5, w: float = 3.0) -> Job:
    out = []
    for i, passes in enumerate(layers):
        ps = tuple(Pass("perimeter", w, 100.0, 300.0, 5.0, pts, None, ax) for pts, ax in passes)
        out.append(Layer(i, (i + 1) * h, h, ps))
    return Job(Source("t", "0", "mm"), {}, BeadInfo(w, h, 2.5, "x"), tuple(out), {})


def test_nozzle_cone_hitting_the_built_part_is_named_by_layer_and_point():
    wall = np.array([[0.0, y, 0.0] for y in np.linspace(-10, 10, 21)])
    layers = [[(wall + [0, 0, (i + 1) * 0.5], None)] for i in range(20)]  # a wall 10 mm tall at x = 0
    low = np.array([[4.0, y, 0.5] for y in np.linspace(-5, 5, 11)])  # a bead beside its foot ...
    ax = np.tile([-np.sin(np.radians(70)), 0.0, np.cos(np.radians(70))], (11, 1))  # ... torch leaning into it
    job = _job(layers + [[(low, ax)]])
    hits = collisions(job, Nozzle(15.0, 60.0, 3.0))
    assert hits and hits[0]["layer"] == 20 and hits[0]["pass"] == 0 and hits[0]["point"] == 0
    upright = _job(layers + [[(low, np.tile([0, 0, 1.0], (11, 1)))]])
    assert collisions(upright, Nozzle(15.0, 60.0, 3.0)) == []


def test_tool_axes_are_smooth_along_the_bead_and_unit():
    from planner.plan import PlanOptions, plan_part
    from core.config import load_material

    job = plan_part(cone_frustum(height=1.5), PlanOptions(width_mm=3.0, five_axis=FiveAxisOptions()),
                    load_material("inconel718-1.0mm"))
    for L in job.layers[1:]:
        for p in L.passes:
            assert np.allclose(np.linalg.norm(p.axes, axis=1), 1.0, atol=1e-4)
            step = np.degrees(np.arccos(np.clip((p.axes[1:] * p.axes[:-1]).sum(axis=1), -1, 1)))
            seg = np.linalg.norm(np.diff(p.points, axis=0), axis=1)
            # the axis turns with the ring (45° tilt on r ≈ 11 mm: ≈ 3.7°/mm), never faster, never jumps
            assert (step <= 6.0 * seg + 1.5).all(), (step.max(), seg[np.argmax(step)])
    three = dataclasses.replace(job, layers=tuple(dataclasses.replace(L, passes=tuple(
        dataclasses.replace(p, axes=None) for p in L.passes)) for L in job.layers))
    assert overhangs(three) and not overhangs(tool_axes(three, FiveAxisOptions()))


# The G-code of the last completed tube build on A/B (its simulator's log), for the grblHAL dialect
# test below: any completed build's lines serve it, so it does not build the tube a second time
# (about 20 s). A rerun of the build test builds afresh and replaces it.
_TUBE_AB_GCODE: list[list[str]] = []


def _gcode(log: Path) -> list[str]:
    """The lines the CNC simulator received, from its log."""
    return [json.loads(s)["line"] for s in (log / "cnc.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("part,table", [("tube", "AB"), ("frustum", "AC")])
async def test_five_axis_build_on_the_cnc_simulator_lands_on_the_plan(part, table, tmp_path: Path):
    from bench.five_axis import bead_gaps, executed_mid_dev

    mesh = tilted_tube(height=1.2) if part == "tube" else cone_frustum(height=1.2)
    job = plan5(mesh)
    for la in job["layers"]:   # slower beads: the link can feed them at a time scale a test affords
        for p in la["passes"]:
            p["speed_mm_min"] = np.divide(p["speed_mm_min"], 4.0).tolist()   # one, or one per segment (cell-job/2)
    # time scale 30 (lowered to what the link can feed), on a grblHAL-sized RX ring (1024 bytes:
    # bench/five_axis.kin_cfg); the simulators in `cell sim up` beside this
    # process, the demo's topology: in this interpreter their deposit computation and answers took
    # the interpreter lock from the streaming, and under load the CNC's planner ran empty (the tube
    # at time scale 10: 12.4 s standing still in 20 s in one process, 2.2 s beside it; bench/five_axis.py)
    res, log = await build(job, tmp_path, table, scale=30.0, beside=True)
    assert res.state == "complete", res
    mid = executed_mid_dev(job, log, table)
    assert mid["max_mid_dev_mm"] <= 0.02 and mid["max_quarter_dev_mm"] <= 0.02, mid  # chord tolerance (issue 29)
    g = bead_gaps(log)
    assert g["still_s"] < 0.02 * g["moving_s"], g   # fed: the torch moves while the process is on
    f = figures(job, log)
    # nothing lost, nothing twice; a line over several planned points lays their chord, up to
    # (8/3)·s²/L shorter (s ≤ 0.02 mm off the plan, L ≈ 1 mm: under 0.1 %) (issue 38)
    assert abs(f["deposited_mm"] - f["planned_mm"]) < 0.05 + 0.001 * f["planned_mm"], f
    assert f["max_dev_mm"] < 0.05, f                            # on the plan in the workpiece frame
    # tool axis: the moves split for the chord tolerance (issue 29) turn the table linearly in A/B|C
    # between two planned axes, so mid-split the axis may sit off the part-frame interpolation by part of
    # the planned step (measured 4.8° at a 7.6° step on the tube); never more than the step itself
    assert f["max_axis_err_deg"] < max(1.0, 0.7 * f["max_planned_axis_step_deg"]), f
    assert f["max_speed_err"] < 0.02, f                         # tool-tip speed within 2 %
    assert f["max_rotary_step_deg"] <= 2.0 * f["max_planned_axis_step_deg"] + 0.01, f  # no flips
    gcode = _gcode(log)
    assert "G93" in gcode and gcode.count("G93") <= gcode.count("G94")  # G94 restored after each bead
    assert any(("C" if table == "AC" else "B") in g and g.startswith("G1") for g in gcode)
    if (part, table) == ("tube", "AB"):
        _TUBE_AB_GCODE[:] = [gcode]


async def test_executor_gcode_runs_on_grblhal_five_axes(tmp_path: Path):
    """The G-code the CNC executor streamed for the tilted tube (read back from the simulator's
    log) runs on the real grblHAL (5 axes, ../shared/peers) with every line answered ok, in order:
    the rotary words, G93 inverse-time feeds and G94 are the firmware's own dialect."""
    import asyncio

    from tests.peers import firmware

    try:
        await asyncio.to_thread(firmware.build, "grblhal")
    except firmware.PeerUnavailable as e:
        pytest.skip(str(e))
    if _TUBE_AB_GCODE:   # the tube built on A/B by the test above (the same worker runs this file in order)
        gcode = _TUBE_AB_GCODE[0]
    else:
        res, log = await build(plan5(tilted_tube(height=0.6)), tmp_path, "AB", scale=20.0)
        assert res.state == "complete", res
        gcode = _gcode(log)
    # what leads to the first bead of the tube, its first four moves and its closing lines: the
    # firmware runs at real time (the whole bead is 3 min of motion; its dialect is in any part), set
    # up as a fast machine (its defaults: 500 °/min and 10 mm/s² on every axis); even so its simulator
    # took about 1.1 s per move of this program, whatever the feed (measured)
    g93 = gcode.index("G93")
    first_m5 = next(i for i, g in enumerate(gcode) if g.startswith("M5") and i > g93)
    prog = gcode[:min(g93 + 5, first_m5)] + gcode[first_m5:first_m5 + 2]
    assert "G93" in prog and any("A" in g and "B" in g for g in prog if g.startswith("G1"))
    # the firmware simulator is time-shared: beside the other test worker's real-time simulators
    # it can go quiet for seconds, which says nothing about the G-code (a 30 s link timeout)
    out, axes = await firmware.stream_program("grblhal", prog, fast=True)
    assert axes == 5, axes   # read from the firmware's status report
    assert out.acked == out.lines == len(prog)


async def test_robot_movl_carries_the_planned_tool_axis(tmp_path: Path):
    """The robot is sent the planned axis per point (not a fixed vertical), read back from its log."""
    import json

    from tests.cells import Cell, small_job

    job = small_job(n_layers=1)
    tilt = np.radians(30.0)
    for p in job["layers"][0]["passes"]:
        n = len(p["points"])
        p["axes"] = [[np.sin(tilt) * np.cos(k), np.sin(tilt) * np.sin(k), np.cos(tilt)] for k in range(n)]
    async with Cell(tmp_path, scale=20) as c:
        c.ctl.open_job(job_from_dict(job))
        res = await c.ctl.start()
    assert res.state == "complete"
    rows = [json.loads(s) for s in (tmp_path / "log" / "robot.jsonl").read_text().splitlines()]
    movl = [r for r in rows if r["verb"] == "MOVL"]
    assert movl and all("axis" in r for r in movl)
    tilts = np.degrees(np.arccos(np.array([r["axis"][2] for r in movl])))
    # tilted as planned: 30° at the planned points, a normalised blend between them (never vertical)
    assert abs(tilts.max() - 30.0) < 0.01 and tilts.min() > 25.0
    starts = [r for r in rows if r["verb"] == "MOVJ"]
    assert all(abs(np.degrees(np.arccos(r["axis"][2])) - 30.0) < 0.01 for r in starts)  # approach along it

"""`cell-job/2`: a pass's speed and wire feed per segment, read, checked and carried to every program.

A user plans (or edits) a job whose corners run faster than its straights; the file says so with
arrays, the cell refuses a segment it cannot do by name, and every program the cell writes moves
each segment at its own speed.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controller.defaults import SIM_REPLY_TIMEOUT_MS

from controller.export import export_job
from controller.export.gcode import parse_gcode
from controller.export.krl import parse_krl
from controller.export.rapid import parse_rapid
from controller.job.check import JobCheckError, check_job
from controller.job.read import job_from_dict
from controller.runtime.bead_check import judge
from controller.runtime.bead_measure import Pace
from controller.runtime.bead_plan import move_plan
from core.config import load_cell, load_material
from core.errors import InputError
from core.material import ProcessTolerance
from planner.job import job_to_json, loads_job
from tests.jobs import JobSpec, PassSpec, job_object, line, small_job, square

SPEEDS = [600.0, 450.0, 600.0, 750.0]
WFS = [5.5, 5.0, 5.5, 6.0]


def _v2(**kw: object) -> PassSpec:
    return PassSpec(square(20.0), speed=kw.get("speed", SPEEDS), wfs=kw.get("wfs", WFS))  # type: ignore[arg-type]


def test_a_job_with_per_segment_arrays_is_cell_job_2_and_reads_back_the_same() -> None:
    obj = job_object([[_v2()], [PassSpec(square(20.0))]])
    assert obj["schema"] == "cell-job/2"
    p0 = obj["layers"][0]["passes"][0]
    assert p0["speed_mm_min"] == SPEEDS and p0["wfs_m_min"] == WFS
    assert obj["layers"][1]["passes"][0]["speed_mm_min"] == 600.0       # a plain pass keeps its number
    job = loads_job(json.dumps(obj))
    p = job.layers[0].passes[0]
    np.testing.assert_array_equal(p.speeds(), SPEEDS)
    np.testing.assert_array_equal(p.wire_feeds(), WFS)
    lens = p.segment_lengths()
    assert p.speed_mm_min == pytest.approx(float(np.sum(lens * SPEEDS) / lens.sum()))   # length-weighted mean
    assert p.arc_time_s == pytest.approx(float(np.sum(lens / SPEEDS)) * 60.0)
    assert job_to_json(job) == job_to_json(loads_job(job_to_json(job)))                # same bytes again


def test_a_cell_job_1_file_still_reads_and_writes_as_cell_job_1() -> None:
    obj = job_object([[PassSpec(square(20.0))]])
    assert obj["schema"] == "cell-job/1"
    job = job_from_dict(obj)
    assert not job.layers[0].passes[0].per_segment
    assert json.loads(job_to_json(job.job))["schema"] == "cell-job/1"


@pytest.mark.parametrize("edit, message", [
    (lambda o: o.update(schema="cell-job/3"), "schema is 'cell-job/3', which this controller does not know"),
    (lambda o: o.update(schema="cell-job/1"), "layers[0].passes[0].speed_mm_min is a list (per-segment values): "
                                              "that is cell-job/2"),
    (lambda o: o["layers"][0]["passes"][0].update(speed_mm_min=[600.0, 600.0]),
     "layers[0].passes[0].speed_mm_min has 2 values for 4 segments (5 points)"),
    (lambda o: o["layers"][0]["passes"][0]["wfs_m_min"].__setitem__(2, -1.0),
     "layers[0].passes[0].wfs_m_min[2] must be a number > 0"),
])
def test_a_bad_cell_job_2_is_refused_naming_the_field(edit, message) -> None:
    obj = job_object([[_v2()]])
    edit(obj)
    with pytest.raises(InputError) as exc:
        job_from_dict(obj, "part.json")
    assert str(exc.value).startswith("part.json: ") and message in str(exc.value)


def test_the_cell_check_names_the_segment_outside_the_limits() -> None:
    cfg, mat = load_cell(), load_material("inconel718-1.0mm")
    fast = cfg.limits.max_speed_mm_min + 100.0
    with pytest.raises(JobCheckError) as exc:
        check_job(small_job([[_v2(speed=[600.0, 600.0, fast, 600.0])]]), cfg, mat, "part.json")
    assert f"speed_mm_min[2] (segment 2) {fast:g} is outside" in str(exc.value)
    hi = mat.ribeiro.wfs_max_m_min + 1.0
    with pytest.raises(JobCheckError) as exc:
        check_job(small_job([[_v2(wfs=[5.5, hi, 5.5, 5.5])]]), cfg, mat, "part.json")
    assert f"wfs_m_min[1] (segment 1) {hi:g} m/min is outside" in str(exc.value)
    check_job(small_job([[_v2()]]), cfg, mat, "part.json")   # every segment inside: it may run


def _export(obj: dict, fmt: str, tmp_path: Path) -> list[list[str]]:
    res = export_job(job_from_dict(obj), fmt, name="v2_job", out=tmp_path / f"v2_job.{fmt}", clearance_mm=10.0,
                     travel_mm_min=3000.0)
    return list(res.files.values())


def test_gcode_gives_every_line_its_segments_feed(tmp_path: Path) -> None:
    obj = job_object([[_v2()]])
    (lines,) = _export(obj, "gcode", tmp_path)
    (got,) = parse_gcode(lines)
    np.testing.assert_allclose(got.feeds, SPEEDS)
    assert got.wfs is not None
    np.testing.assert_allclose(got.wfs, WFS)
    assert sum(1 for ln in lines if ln.startswith("G1 X") and " F" in ln) == 4   # every move changes speed


def test_rapid_names_a_speeddata_per_move_and_passes_rapidchecker(tmp_path: Path) -> None:
    obj = job_object([[_v2()], [PassSpec(square(20.0))]])
    (lines,) = _export(obj, "rapid", tmp_path)
    got = parse_rapid(lines)
    assert got[0].speeds is not None and got[0].wfs is not None
    np.testing.assert_allclose(got[0].speeds, SPEEDS, atol=0.01)
    np.testing.assert_allclose(got[0].wfs, WFS)
    assert sum(1 for ln in lines if "CONST speeddata vP0_" in ln) == 3   # 3 distinct (speed, wfs) pairs
    assert any("ArcL " in ln and ",vP0_1,smCell,wdP0_1," in ln for ln in lines)
    np.testing.assert_allclose(got[1].speeds, [600.0] * 4, atol=0.01)      # the plain pass: one welddata
    mod = tmp_path / "v2.mod"
    mod.write_text("\n".join(lines) + "\n")
    ok = subprocess.run([sys.executable, "-m", "rapidchecker", str(mod)], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stdout + ok.stderr


def test_krl_sets_vel_cp_before_every_move_that_changes_speed(tmp_path: Path) -> None:
    obj = job_object([[_v2()]])
    src, dat = _export(obj, "krl", tmp_path)
    (got,) = parse_krl(src, dat)
    np.testing.assert_allclose(got.speeds, SPEEDS, atol=0.01)
    np.testing.assert_allclose(got.wfs, WFS)
    on = next(i for i, ln in enumerate(src) if ln.startswith("WELD_ON("))
    weld = src[on:src.index("WELD_OFF( )", on)]
    assert sum(1 for ln in weld if ln.startswith("$VEL.CP = ")) == 4


def test_the_runner_streams_each_move_at_its_segment_speed_and_judges_against_the_range() -> None:
    job = small_job([[PassSpec(line(10.0, n=3), speed=[600.0, 300.0], wfs=[4.5, 6.5])]])
    plan = move_plan(job.layers[0].passes[0], max_step_mm=2.0)
    assert plan.speeds == [600.0] * 3 + [300.0] * 3 and plan.wfs == [4.5] * 3 + [6.5] * 3
    assert plan.plan_t is not None and plan.plan_t[-1] == pytest.approx(0.5 + 1.0)   # 5 mm at 10 mm/s, 5 at 5
    tol = ProcessTolerance()
    ok = {"i_mean": 120.0, "i_min": 110.0, "i_max": 130.0, "u_mean": 20.0, "u_min": 19.0, "u_max": 21.0,
          "wfs_mean": 5.5, "wfs_min": 4.5, "wfs_max": 6.5}
    assert judge(ok, 120.0, plan.wfs_range(), tol, False) is None        # 4.5-6.5 m/min is the plan
    assert "wire feed 4.50-6.50 m/min outside 5.50 m/min" in (judge(ok, 120.0, 5.5, tol, False) or "")
    # the pace: half the bead at 10 mm/s then half at 5 mm/s is no stand-still
    pace = Pace(0.0, 0.0, planned_mm_min=job.layers[0].passes[0].speed_mm_min, plan_s=plan.plan_s, plan_t=plan.plan_t)
    for t, s in ((0.2, 2.0), (0.4, 4.0), (0.7, 6.0), (1.1, 8.0), (1.5, 10.0)):
        pace.reached(t, s)
    assert pace.standstill(1.0)["still_n"] == 0
    flat = Pace(0.0, 0.0, planned_mm_min=job.layers[0].passes[0].speed_mm_min)   # judged at one speed, it would be
    for t, s in ((0.2, 2.0), (0.4, 4.0), (0.7, 6.0), (1.1, 8.0), (1.5, 10.0)):
        flat.reached(t, s)
    assert (flat.standstill(1.0)["still_n"] or 0) > 0


def test_a_small_job_spec_sets_the_material_and_layers() -> None:
    job = small_job([[PassSpec(line(10.0))], [PassSpec(line(10.0))]], JobSpec(layer_height=1.5))
    assert [la.z_mm for la in job.layers] == [1.5, 3.0]
    assert job.job.material["name"] == "inconel718-1.0mm"


@pytest.mark.realtime   # a cell on the wall clock (tests/conftest.py)
async def test_a_robot_build_moves_each_segment_at_its_speed_and_records_the_range(tmp_path: Path) -> None:
    from controller.harness.cell import open_cell, with_urls
    from core.config import load_sim

    speeds = [600.0, 300.0, 900.0]
    job = small_job([[PassSpec(line(24.0, n=4), speed=speeds, wfs=[5.5, 5.0, 6.0])]])
    cfg = with_urls(load_cell(), {}, time_scale=10)
    async with open_cell(cfg, sim=load_sim(), log_dir=tmp_path / "log", runs_dir=tmp_path / "runs",
                         reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        ctl.open_job(job)
        res = await ctl.start()
        report = json.loads(ctl.write_report().read_text())
    assert res.state == "complete" and res.defects == 0
    rows = [json.loads(ln) for ln in (tmp_path / "log" / "robot.jsonl").read_text().splitlines()]
    moves = [r for r in rows if r.get("verb") == "MOVL"]
    pts = np.array([r["target"] for r in moves])
    t = np.array([r["t"] for r in moves])
    v = np.linalg.norm(np.diff(pts, axis=0), axis=1) / np.diff(t) * 60.0   # the log is in process time
    x_mid = 0.5 * (pts[1:, 0] + pts[:-1, 0])
    for k, want in enumerate(speeds):   # segment k spans x in [8k, 8k + 8]
        got = np.median(v[(x_mid > 8 * k + 1) & (x_mid < 8 * k + 7)])
        assert got == pytest.approx(want, rel=0.05), (k, got)
    assert report["state"] == "complete"
    csv = next((tmp_path / "runs").glob("*/beads.csv")).read_text().splitlines()
    head, first = csv[0].split(","), csv[1].split(",")
    row = dict(zip(head, first))
    assert float(row["speed_planned_min_mm_min"]) == 300.0 and float(row["speed_planned_max_mm_min"]) == 900.0
    assert float(row["speed_planned_mm_min"]) == pytest.approx(600.0)   # length-weighted mean of equal segments

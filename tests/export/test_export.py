"""Program export (`cell export`): G-code, ABB RAPID and KUKA KRL, each read back to the job.

The round trip is the user's check that the program says what the plan says: every point,
the travel speed and the welding parameters of every pass, within the rounding of the format.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controller.motion.kinematics import homogeneous, rotation_matrix
from controller.export import export_job
from controller.job.read import job_from_dict
from controller.export.gcode import parse_gcode
from controller.export.krl import parse_krl
from controller.export.rapid import parse_rapid


def _job(axes: bool = False, alignment: np.ndarray | None = None) -> dict:
    rng = np.random.default_rng(5)
    layers = []
    for li in range(3):
        passes = []
        for pi in range(2):
            pts = np.round(np.column_stack([np.linspace(0, 40, 6) + 10 * pi, rng.uniform(-20, 20, 6),
                                            np.full(6, 0.8 * (li + 1))]), 3)
            p = {"role": "perimeter" if pi == 0 else "infill", "width_mm": 6.0 + pi, "current_a": 140.5 + li,
                 "speed_mm_min": 1200.0 + 10 * li + pi, "wfs_m_min": 6.25 + 0.1 * pi, "points": pts.tolist()}
            if axes:
                tilt = np.radians(20 + 5 * li)
                ax = np.column_stack([np.full(6, math.sin(tilt)), np.zeros(6), np.full(6, math.cos(tilt))])
                p["axes"] = ax.tolist()
            passes.append(p)
        layers.append({"index": li, "z_mm": 0.8 * (li + 1), "height_mm": 0.8, "passes": passes,
                       "interpass": {"max_temperature_c": 200.0, "dwell_s": 12.5}})
    job = {"schema": "cell-job/1", "source": {"file": "t.stl", "sha256": "ab" * 32, "units": "mm"},
           "material": {"name": "inconel718-1.0mm"},
           "bead": {"width_mm": 6.0, "height_mm": 0.8, "step_over_mm": 4.4, "model": "tangent"},
           "layers": layers, "summary": {}}
    if alignment is not None:
        job["frame"] = "cad"
        job["alignment"] = {"transform": alignment.tolist(), "points_in_machine_frame": False}
    return job


def _planned(job: dict):
    for L in job["layers"]:
        for i, p in enumerate(L["passes"]):
            yield L["index"], i, p


def _export(job: dict, fmt: str, tmp_path: Path):
    res = export_job(job_from_dict(job), fmt, name="t_job", out=tmp_path / f"t_job.{fmt}", clearance_mm=10.0,
                     travel_mm_min=3000.0)
    return res, list(res.files.values())


ALIGN = homogeneous(rotation_matrix("z", 4.0) @ rotation_matrix("x", 1.5), [12.0, -7.0, 3.0])


@pytest.mark.parametrize("aligned", [False, True])
def test_gcode_round_trip_gives_the_jobs_points_speeds_and_parameters(tmp_path, aligned):
    job = _job(alignment=ALIGN if aligned else None)
    res, (lines,) = _export(job, "gcode", tmp_path)
    got = parse_gcode(lines)
    assert res.passes == len(got) == 6
    t = ALIGN if aligned else np.eye(4)
    for g, (li, pi, p) in zip(got, _planned(job)):
        assert (g.layer, g.index, g.role) == (li, pi, p["role"])
        want = np.asarray(p["points"]) @ t[:3, :3].T + t[:3, 3]   # the alignment is in the points
        np.testing.assert_allclose(g.points, want, atol=6e-4)
        assert g.speed_mm_min == pytest.approx(p["speed_mm_min"], abs=0.05)
        assert g.current_a == pytest.approx(p["current_a"], abs=0.005)
        assert g.wfs_m_min == pytest.approx(p["wfs_m_min"], abs=5e-4)
    assert lines.count("G4 P12.5") == 2             # interpass dwell before layers 1 and 2
    assert all(len(ln) <= 80 for ln in lines)       # grbl's line buffer
    assert lines[-2:] == ["M5", "M30"]


@pytest.mark.parametrize("aligned", [False, True])
def test_rapid_round_trip_with_the_alignment_as_work_object(tmp_path, aligned):
    job = _job(axes=True, alignment=ALIGN if aligned else None)
    res, (lines,) = _export(job, "rapid", tmp_path)
    got = parse_rapid(lines)
    assert len(got) == 6
    for g, (li, pi, p) in zip(got, _planned(job)):
        assert (g.layer, g.index, g.role) == (li, pi, p["role"])
        np.testing.assert_allclose(g.points, p["points"], atol=6e-4)   # part frame: the wobj moves it
        np.testing.assert_allclose(g.axes, p["axes"], atol=2e-6)
        assert g.speed_mm_min == pytest.approx(p["speed_mm_min"], abs=0.01)
        assert g.current_a == pytest.approx(p["current_a"], abs=0.005)
        assert g.wfs_m_min == pytest.approx(p["wfs_m_min"], abs=5e-4)
    text = "\n".join(lines)
    wobj = next(ln for ln in lines if "PERS wobjdata wobjCell" in ln)
    if aligned:
        assert "[12,-7,3]" in wobj
    else:
        assert "[0,0,0],[1,0,0,0]]" in wobj
    assert text.count("ArcLStart") == text.count("ArcLEnd") == 6
    assert text.count("WaitTime 12.5;") == 2
    assert lines[0] == "MODULE t_job" and lines[-1] == "ENDMODULE"


@pytest.mark.parametrize("aligned", [False, True])
def test_krl_round_trip_with_the_alignment_as_base(tmp_path, aligned):
    job = _job(axes=True, alignment=ALIGN if aligned else None)
    res, (src, dat) = _export(job, "krl", tmp_path)
    assert sorted(Path(f).name for f in res.files) == ["t_job.dat", "t_job.src"]
    got = parse_krl(src, dat)
    assert len(got) == 6
    for g, (li, pi, p) in zip(got, _planned(job)):
        assert (g.layer, g.index, g.role) == (li, pi, p["role"])
        np.testing.assert_allclose(g.points, p["points"], atol=6e-4)
        np.testing.assert_allclose(g.axes, p["axes"], atol=1e-5)
        assert g.speed_mm_min == pytest.approx(p["speed_mm_min"], abs=0.01)
        assert g.current_a == pytest.approx(p["current_a"], abs=0.005)
        assert g.wfs_m_min == pytest.approx(p["wfs_m_min"], abs=5e-4)
    base = next(ln for ln in src if ln.startswith("$BASE"))
    assert ("X 12.000,Y -7.000,Z 3.000" in base) == aligned
    assert src.count("WAIT SEC 12.5") == 2
    assert src[2] == "DEF T_JOB( )" and dat[2] == "DEFDAT T_JOB" and dat[-1] == "ENDDAT"


def test_rapid_export_passes_a_third_party_rapid_grammar_checker(tmp_path):
    """rapidchecker (pyparsing, RobotWare grammar) accepts the module and rejects a broken copy."""
    _, (lines,) = _export(_job(axes=True, alignment=ALIGN), "rapid", tmp_path)
    good, bad = tmp_path / "good.mod", tmp_path / "bad.mod"
    good.write_text("\n".join(lines) + "\n")
    bad.write_text("\n".join(ln.replace("ArcLEnd ", "ArcLEnd ,") for ln in lines) + "\n")
    ok = subprocess.run([sys.executable, "-m", "rapidchecker", str(good)], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "No RAPID format errors" in ok.stdout, ok.stdout
    no = subprocess.run([sys.executable, "-m", "rapidchecker", str(bad)], capture_output=True, text=True, timeout=120)
    assert no.returncode == 1 and "Expected ';'" in no.stdout


def test_an_old_style_aligned_job_is_not_transformed_twice(tmp_path):
    """`cell align run --job` moved the points already: the exported G-code keeps them as they are."""
    job = _job()
    moved = json.loads(json.dumps(job))
    for L in moved["layers"]:
        for p in L["passes"]:
            pts = np.asarray(p["points"])
            p["points"] = (pts @ ALIGN[:3, :3].T + ALIGN[:3, 3]).tolist()
    moved["alignment"] = {"transform": ALIGN.tolist()}
    _, (lines,) = _export(moved, "gcode", tmp_path)
    for g, (_, _, p) in zip(parse_gcode(lines), _planned(moved)):
        np.testing.assert_allclose(g.points, p["points"], atol=6e-4)


def test_gcode_streams_on_the_cnc_simulator_every_line_ok(tmp_path):
    """The exported program runs on the grbl-speaking simulator: no error, every weld move run."""
    import asyncio

    from sims.clock import SimClock
    from sims.cnc import CncSim
    from sims.workpiece import Workpiece
    from tests.cnc_fixtures import cnc_link
    from sims.world import World
    from core.config import Workpiece as WorkpieceConfig

    job = _job()
    for L in job["layers"]:
        L["interpass"]["dwell_s"] = 0.2
    _, (lines,) = _export(job, "gcode", tmp_path)

    async def go() -> list[dict]:
        sim = CncSim(clock=SimClock(400.0), world=World(tmp_path), log_path=tmp_path / "cnc.jsonl",
                     workpiece=Workpiece.from_config(WorkpieceConfig(), 0.0, seed=1))
        async with cnc_link(sim) as link:
            await link.connect()
            await link.unlock()
            res = await link.stream(lines)   # raises GrblError on any error:N
            code = [ln for ln in lines if ln and not ln.startswith("(")]
            assert res.acked == res.lines >= len(code)
        return [json.loads(s) for s in (tmp_path / "cnc.jsonl").read_text().splitlines()]

    executed = asyncio.run(go())
    welds = [e for e in executed if e["line"].startswith("G1X")]
    assert len(welds) == sum(len(p["points"]) - 1 for _, _, p in _planned(job))


def test_cli_export_json_and_errors(tmp_path):
    job = tmp_path / "part.job.json"
    job.write_text(json.dumps(_job()))
    out = tmp_path / "prog.mod"
    r = subprocess.run([sys.executable, "-m", "controller.cli.main", "export", str(job), "--format", "rapid",
                        "--out", str(out), "--json"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["format"] == "rapid" and info["passes"] == 6 and info["out"] == str(out)
    assert info["lines"] == len(out.read_text().splitlines())
    bad = tmp_path / "bad.job.json"
    bad.write_text('{"schema": "cell-job/1"}')
    r = subprocess.run([sys.executable, "-m", "controller.cli.main", "export", str(bad), "--format", "krl"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr
    assert "source" in r.stderr


def _tiny_job(axes: bool) -> dict:
    """Two short layers: quick on firmware that runs at a third of real time."""
    job = _job(axes=axes)
    job["layers"] = job["layers"][:2]
    job["schema"] = "cell-job/2"
    for L in job["layers"]:
        L["interpass"]["dwell_s"] = 0.1
        L["passes"] = L["passes"][:1]
        p = L["passes"][0]
        p["points"] = [[x, 5.0, L["z_mm"]] for x in (0.0, 4.0, 8.0)]
        p["speed_mm_min"] = [3000.0, 2400.0]     # cell-job/2: a speed per segment
        if axes:
            p["axes"] = p["axes"][:3]
    return job


def test_five_axis_gcode_round_trips_through_the_tables_kinematics(tmp_path):
    """G93 X Y Z A B: forward kinematics of what the program commands gives the planned part points
    and tool axes back, and each inverse-time F makes the tool tip move at the planned speed."""
    from controller.motion.kinematics import Trunnion

    table = Trunnion()
    job = _job(axes=True)
    res = export_job(job_from_dict(job), "gcode", name="t5", out=tmp_path / "t5.nc", clearance_mm=10.0, travel_mm_min=3000.0,
                     trunnion=table)
    lines = list(res.files.values())[0]
    assert "G93" in lines and "G94" in lines and all(len(ln) <= 80 for ln in lines)
    got = parse_gcode(lines)
    from bench.five_axis import _seg_dist
    from controller.motion.lines5 import part_points

    for g, (_, _, p) in zip(got, _planned(job)):
        pts = np.asarray(p["points"])
        rows = np.column_stack([g.points, g.rotary])
        back = [table.forward(r) for r in rows]
        # a line may run over several planned points (issue 38): its ends lie on the planned path,
        # from the first point to the last, and the tool tip stays within 0.02 mm of it mid-move
        assert _seg_dist(np.array([b[0] for b in back]), pts[:-1], pts[1:]).max() < 2e-3
        np.testing.assert_allclose([back[0][0], back[-1][0]], [pts[0], pts[-1]], atol=2e-3)
        mids = part_points(table, np.vstack([rows[:-1] + (rows[1:] - rows[:-1]) * f for f in (0.25, 0.5, 0.75)]))
        assert _seg_dist(mids, pts[:-1], pts[1:]).max() <= 0.02
        tilt = np.degrees(np.arccos(np.clip([b[1][2] for b in back], -1, 1)))
        planned_tilt = np.degrees(np.arccos(np.clip(np.asarray(p["axes"])[:, 2], -1, 1)))
        assert planned_tilt.min() - 0.05 <= tilt.min() and tilt.max() <= planned_tilt.max() + 0.05
        # inverse time: the lines take the planned time (F = 1 / minutes of each line)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        np.testing.assert_allclose((1.0 / g.feeds).sum(), seg.sum() / p["speed_mm_min"], rtol=1e-3)


@pytest.mark.parametrize("kind,axes", [("grbl", False), ("grblhal", False), ("grblhal", True)])
async def test_exported_gcode_runs_on_real_firmware_every_line_ok(tmp_path, kind, axes):
    """The exported program on grbl 1.1h / grblHAL (../shared/peers, built by tests/peers):
    every line answered ok, in order; the 5-axis program (X Y Z A B, G93) on grblHAL."""
    import asyncio

    from controller.motion.kinematics import Trunnion
    from tests.peers import firmware

    try:
        await asyncio.to_thread(firmware.build, kind)
    except firmware.PeerUnavailable as e:
        pytest.skip(str(e))
    res = export_job(job_from_dict(_tiny_job(axes)), "gcode", name="fw", out=tmp_path / "fw.nc", clearance_mm=2.0,
                     travel_mm_min=3000.0, trunnion=Trunnion())
    lines = list(res.files.values())[0]
    code = [ln for ln in lines if not ln.startswith("(")]
    out, _axes = await firmware.stream_program(kind, lines, fast=True)   # GrblError names the first refused line
    assert out.acked == out.lines >= len(code)
    assert any(ln.startswith("M4 S") for ln in code) and any("F2400" in ln for ln in code) or axes

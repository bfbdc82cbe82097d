"""`cell plan`: the command-line contract of docs/contract.md §7, outputs, and clear failures."""
from __future__ import annotations

import json
import re

import pytest

from controller.cli.main import main
from planner.job import loads_job

from tests import planner_parts as parts


@pytest.fixture
def stl(tmp_path):
    p = tmp_path / "plate.stl"
    p.write_bytes(parts.plate_with_holes().export(file_type="stl"))
    return p


def test_plan_json_summary_job_file_and_previews(stl, tmp_path, capsys):
    out = tmp_path / "jobs" / "plate.json"
    rc = main(["plan", str(stl), "--width", "6", "--out", str(out), "--preview", str(tmp_path / "pv"), "--json"])
    captured = capsys.readouterr()
    assert rc == 0
    summary = json.loads(captured.out)  # exactly one JSON object on stdout
    for key in ("layers", "passes", "arc_starts", "deposit_length_mm", "volume_mm3", "coverage", "est_time_s",
                "underfill", "overfill", "repairs", "open_contours"):
        assert key in summary
    job = loads_job(out.read_bytes())
    assert summary["layers"] == len(job.layers) == 9  # 6 mm plate / 0.66 mm layers
    assert summary["passes"] == sum(len(L.passes) for L in job.layers)
    assert summary["coverage"] >= 0.98
    for name in ("layers.png", "overview.png"):
        data = (tmp_path / "pv" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_layer_height_and_perimeters_flags(stl, tmp_path, capsys):
    out = tmp_path / "p.json"
    assert main(["plan", str(stl), "--width", "6", "--layer-height", "0.6", "--perimeters", "1",
                 "--out", str(out), "--json"]) == 0
    job = loads_job(out.read_bytes())
    assert job.bead.height_mm == 0.6 and len(job.layers) == 10
    assert all(L.extra["perimeter_loops"] <= 4 for L in job.layers)  # one loop per boundary


def test_inch_units_scale_the_part(tmp_path, capsys):
    p = tmp_path / "small.stl"
    p.write_bytes(parts.extrude(parts.box(0, 0, 2, 1.5), 0.2).export(file_type="stl"))
    assert main(["plan", str(p), "--width", "6", "--units", "inch", "--out", str(tmp_path / "j.json"),
                 "--json"]) == 0
    job = loads_job((tmp_path / "j.json").read_bytes())
    xs = [pt[0] for L in job.layers for q in L.passes for pt in q.points]
    assert max(xs) - min(xs) > 40  # 2 in = 50.8 mm, beads half a bead inside
    assert job.source.units == "inch"


@pytest.mark.parametrize("argv, words", [
    (["--width", "6", "--units", "furlong"], "invalid choice"),
    (["--width", "-1"], "positive"),
    (["--width", "6", "--perimeters", "lots"], "perimeters"),
    (["--width", "60"], "outside|below|above"),
])
def test_bad_flags_exit_2_with_one_error_line(stl, argv, words, capsys):
    try:
        rc = main(["plan", str(stl), *argv])
    except SystemExit as exc:  # argparse's usage errors leave through SystemExit(2)
        rc = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:")
    assert re.search(words, err[0])


def test_empty_mesh_exits_2(tmp_path, capsys):
    p = tmp_path / "e.stl"
    p.write_bytes(b"solid x\nendsolid x\n")
    rc = main(["plan", str(p), "--width", "6"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"error: {p}: the mesh has no triangles; export the part again as a solid"]


def test_no_progress_bar_on_stdout_for_json(stl, tmp_path, capsys):
    main(["plan", str(stl), "--width", "6", "--out", str(tmp_path / "j.json"), "--json"])
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and "planning" not in out

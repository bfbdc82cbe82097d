"""`cell finish plan JOB --json --out PROGRAM` (issue 36 item 6): a near-net build's top face."""
from __future__ import annotations

import json
import re
from pathlib import Path

import trimesh

from controller.cli.main import main


def test_finish_plan_of_a_planned_block_writes_a_milling_program_that_stays_on_cad(tmp_path: Path, capsys):
    trimesh.creation.box(extents=(30, 20, 8)).export(tmp_path / "part.stl")
    job = tmp_path / "part.job.json"
    assert main(["plan", str(tmp_path / "part.stl"), "--width", "4", "--out", str(job)]) == 0
    capsys.readouterr()
    prog = tmp_path / "part.nc"
    assert main(["finish", "plan", str(job), "--json", "--out", str(prog)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"tool", "passes", "removal_mm3", "est_time_s", "min_stock_mm", "scallop_mm"} <= set(out)
    assert out["tool"] == "ball6" and out["scallop_mm"] <= 0.01
    lines = prog.read_text().splitlines()
    assert lines[:4] == ["$32=0", "G49", "T1 M6", "G43.1 Z0.000"] and "M3 S12000" in lines and lines[-1] == "M5"
    zs = [float(m.group(1)) for s in lines if s.startswith("G1") for m in [re.search(r"Z(-?\d+\.\d+)", s)] if m]
    top = max(float(v) for v in re.findall(r"Z(-?\d+\.\d+)", "".join(s for s in lines if s.startswith("G1"))))
    assert zs and min(zs) >= top - 1e-9      # a flat top face: every cut at the CAD top, none below
    assert main(["finish", "plan", str(job), "--tool", "nope"]) == 2
    assert "no cutter 'nope'" in capsys.readouterr().err


def test_finish_plan_json_prints_one_object_on_every_exit(tmp_path: Path, capsys):
    """A bad cutter, an unwritable program, a job with no CAD: exit 2, one JSON object naming it."""
    trimesh.creation.box(extents=(30, 20, 8)).export(tmp_path / "part.stl")
    job = tmp_path / "part.job.json"
    assert main(["plan", str(tmp_path / "part.stl"), "--width", "4", "--out", str(job)]) == 0
    capsys.readouterr()
    nocad = tmp_path / "nocad.job.json"
    d = json.loads(job.read_text())
    d["source"]["file"] = "gone.stl"
    nocad.write_text(json.dumps(d))
    for argv, says in ((["--tool", "nope"], "no cutter 'nope'"), (["--out", str(tmp_path / "no" / "x.nc")], "x.nc"),
                       ([], "gone.stl")):
        src = str(nocad if not argv else job)
        code = main(["finish", "plan", src, "--json", *argv])
        out, err = capsys.readouterr()
        objs = [json.loads(s) for s in out.splitlines() if s.strip()]
        assert code == 2 and len(objs) == 1 and objs[0]["exit_code"] == 2, (argv, out, err)
        assert says in objs[0]["error"] and err.startswith("error: ") and says in err, (argv, objs, err)


def test_export_gcode_finish_writes_the_milling_program_beside_the_deposition(tmp_path: Path, capsys):
    """`cell export --format gcode --finish` (issue 36 item 6): the deposition program and the
    milling program of the top faces, `$32=0` first, the tool change, every cut on the CAD or above."""
    trimesh.creation.box(extents=(30, 20, 8)).export(tmp_path / "part.stl")
    job = tmp_path / "part.job.json"
    assert main(["plan", str(tmp_path / "part.stl"), "--width", "4", "--out", str(job)]) == 0
    capsys.readouterr()
    out = tmp_path / "part.nc"
    assert main(["export", str(job), "--format", "gcode", "--finish", "--firmware", "grbl", "--out", str(out),
                 "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    mill = tmp_path / "part.finish.nc"
    assert obj["files"] == [str(out), str(mill)] and obj["finish"]["out"] == str(mill)
    assert obj["finish"]["tool"] == "ball6" and obj["finish"]["scallop_mm"] <= 0.01
    lines = mill.read_text().splitlines()
    assert len(lines) == obj["finish"]["lines"]
    assert lines[0] == "$32=0" and "T1 M0" in lines[:5] and "M3 S12000" in lines and lines[-1] == "M5"
    dep = out.read_text()   # the deposition program: M4 (power follows the speed, docs/laser-power.md); it sets no $32
    assert "M4 S" in dep and not any(ln.startswith("$32") for ln in dep.splitlines())
    zs = [float(z) for s in lines if s.startswith("G1") for z in re.findall(r"Z(-?\d+\.\d+)", s)]
    assert zs and min(zs) >= 8.0 - 1e-9       # the block's top (z = 8 in the job's frame): nothing below
    code = main(["export", str(job), "--format", "krl", "--finish", "--json"])
    err = capsys.readouterr()
    assert code == 2 and "milling program is G-code" in json.loads(err.out)["error"]

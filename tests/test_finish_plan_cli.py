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
    assert lines[:3] == ["G49", "T1 M6", "G43.1 Z0.000"] and "M3 S12000" in lines and lines[-1] == "M5"
    zs = [float(m.group(1)) for s in lines if s.startswith("G1") for m in [re.search(r"Z(-?\d+\.\d+)", s)] if m]
    top = max(float(v) for v in re.findall(r"Z(-?\d+\.\d+)", "".join(s for s in lines if s.startswith("G1"))))
    assert zs and min(zs) >= top - 1e-9      # a flat top face: every cut at the CAD top, none below
    assert main(["finish", "plan", str(job), "--tool", "nope"]) == 2
    assert "no cutter 'nope'" in capsys.readouterr().err

"""The command line: `cell demo`, `cell run --sim --fault`, `cell resume`, unreachable devices."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.cells import shorten, small_job

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[2]


def cell(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "controller.cli.main", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, "PYTHONPATH": str(ROOT)})


def _flagged(stdout: str) -> object:
    """What made a run exit non-zero: its defects and alarms (the JSON summary), else its output."""
    try:
        out = json.loads(stdout)
    except ValueError:
        return stdout[-2000:]
    return {"defects": [d.get("message") for d in out.get("defects") or []], "alarms": out.get("alarms")}


@pytest.mark.owns_cpus  # the main job's figures (no bead flagged, speed within 5 %), not the other worker's cell
@pytest.mark.usefixtures("record_plots")  # checks the PNGs (tests/conftest.py)
def test_demo_plans_aligns_builds_and_reports(tmp_path: Path) -> None:
    r = cell("demo", "--json", "--layers", "2", "--runs", str(tmp_path), "--wire-lot", "DEMO-LOT-1",
             "--operator", "demo")
    assert r.returncode == 0, (_flagged(r.stdout), r.stderr[-1500:])
    out = json.loads(r.stdout)
    # 7 beads a layer: the square's inner ring gives way to the hole's in four corner beads (planner/ring_spacing.py)
    assert out["state"] == "complete" and out["layers_done"] == 2 and out["passes_done"] == 14
    report = Path(out["report"])
    rep = json.loads(report.read_text())
    assert rep["passes_done"] == 14 and rep["state"] == "complete"
    # traceability from the command (docs/records.md); the gas is the material's when none is given
    assert (rep["wire_lot"], rep["operator"], rep["gas"]) == ("DEMO-LOT-1", "demo", "Ar 99.99 % (argon), 15 L/min")
    assert {"layers.png", "process.png", "temperature.png", "defects.png"} <= set(rep["plots"])
    assert report.parent.name.startswith("square-hole-") and (report.parent / "journal.sqlite").exists()
    # the substrate of config/sim.yaml is tilted 0.8° / -0.5° and turned 1.5°: the probe finds it
    assert abs(abs(out["alignment"]["face_angle_deg"]) - 1.5) < 0.05
    assert "layer 2/2" in r.stderr  # progress lines while it runs (on stderr with --json)
    # the robot's queue never ran empty inside a bead (the line is paced at the simulated rate)
    assert rep["travel_speed"]["starved_beads"] == 0 and rep["travel_speed"]["beads_measured"] == 14
    # the travel speed timed from the robot's EXEs: the 2 % on every bead is the demo's
    # figure on a quiet machine (docs/build-record.md: worst 0.8-1.0 %); here, beside the other
    # test worker, a looser bound still catches a robot that does not keep pace (was 27 % off)
    # The corner beads (29.1 mm, planner/ring_spacing.py) last about 30 ms of wall time at time scale 60:
    # timed from the robot's reports to a few ms, they read up to ~14 % off; every longer bead within
    # the material's 10 %, and none near a robot that does not keep pace
    ts = rep["travel_speed"]
    with (report.parent / "beads.csv").open() as fh:
        length = {(int(r["layer"]), int(r["pass"])): float(r["length_planned_mm"]) for r in csv.DictReader(fh)}
    assert abs(ts["worst_deviation"]) < 0.2 and all(length[(la, p)] < 30.0 for la, p, _ in ts["off_speed_beads"]), ts
    # every bead deposited its planned length: the plan's arc time and the deposited length at
    # planned speed agree
    a = rep["arc_time_figures"]
    assert abs(a["planned_s"] / a["plan_s"] - 1) < 0.01, a
    assert a["measured_s"] > 0


def test_run_with_an_arc_loss_in_layer_1_then_resume_completes(tmp_path: Path) -> None:
    job = tmp_path / "square.job.json"
    job.write_text(json.dumps(shorten(small_job(n_layers=3), range(0, 1))))
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    cfg["cell"]["time_scale"] = 4.0  # long enough beads for a 0.5 s arc loss to be one
    cfgp = tmp_path / "cell.yaml"
    cfgp.write_text(yaml.safe_dump(cfg))
    r = cell("run", str(job), "--sim", "--fault", "arc_loss@layer=1", "--json", "--runs", str(tmp_path / "runs"),
             "--cell-config", str(cfgp))
    assert r.returncode == 1, r.stderr[-2000:]
    out = json.loads(r.stdout)
    assert out["state"] == "fault" and out["layers_done"] == 1
    assert out["alarms"][0]["layer"] == 1 and "arc" in out["alarms"][0]["message"].lower()
    assert out["alarms"][0]["position"][2] == 2.0
    # the interrupted build ran with --sim: so does `cell resume` without being told
    r = cell("resume", "--json", "--runs", str(tmp_path / "runs"), "--cell-config", str(cfgp))
    assert r.returncode == 0, r.stderr[-2000:]
    out2 = json.loads(r.stdout)
    assert out2["state"] == "complete" and out2["layers_done"] == 3 and out2["passes_done"] == 6
    assert out2["arc_starts"] == 6 - out["passes_done"]
    rep = json.loads(Path(out2["report"]).read_text())
    assert rep["defects"][0]["layer"] == 1 and rep["runs"] == 2


def test_unreachable_device_is_one_error_line_naming_it(tmp_path: Path) -> None:
    cfg = yaml.safe_load((ROOT / "config" / "cell.yaml").read_text())
    cfg["devices"]["robot"]["url"] = "socket://127.0.0.1:9"
    cfgp = tmp_path / "cell.yaml"
    cfgp.write_text(yaml.safe_dump(cfg))
    job = tmp_path / "j.json"
    job.write_text(json.dumps(small_job(1)))
    r = cell("run", str(job), "--cell-config", str(cfgp), "--runs", str(tmp_path / "runs"))
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: robot at socket://127.0.0.1:9"), r.stderr


def test_bad_job_file_is_one_error_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema": "cell-job/1", "layers": [')
    r = cell("run", str(bad), "--sim")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "not valid JSON" in r.stderr

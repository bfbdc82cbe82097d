"""The build record: report.json, one CSV row per bead, `cell report` and `cell runs` (docs/contract.md §7)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from controller.cli.main import main
from controller.job.read import job_from_dict
from tests.cells import Cell, small_job

pytestmark = pytest.mark.realtime  # a cell on the wall clock (tests/conftest.py)


@pytest.mark.usefixtures("record_plots")  # checks the PNGs (tests/conftest.py)
async def test_every_build_leaves_a_record_with_one_csv_row_per_bead(tmp_path: Path, capsys) -> None:
    job = small_job(n_layers=2)
    async with Cell(tmp_path, scale=20) as c:
        run_dir = c.ctl.open_job(job_from_dict(job))
        res = await c.ctl.start()  # no explicit write_report: the API writes it at the end of the build
        trips = [t.message for t in c.ctl.interlocks.trips]
    assert res.state == "complete", trips
    rep = json.loads((run_dir / "report.json").read_text())
    rows = list(csv.DictReader((run_dir / "beads.csv").open()))
    assert len(rows) == len(rep["beads"]) == 4
    b = rep["beads"][0]
    # measured against planned: the sim's source holds the commanded current and feed
    assert b["current_planned_a"] == 120 and 100 < b["current_mean_a"] < 140
    assert b["current_min_a"] <= b["current_p5_a"] <= b["current_mean_a"] <= b["current_p95_a"] <= b["current_max_a"]
    assert b["current_min_a"] <= b["current_mean_a"] <= b["current_max_a"]
    assert b["wfs_planned_m_min"] == 5.5 and b["wfs_mean_m_min"] is not None
    assert b["arc_time_s"] > 0 and b["heat_input_j_mm"] > 0
    assert b["wfs_min_m_min"] <= b["wfs_mean_m_min"] <= b["wfs_max_m_min"]
    assert abs(b["wfs_mean_m_min"] / 5.5 - 1) < 0.05
    # the robot's pace, from its EXE reports: the planned speed, no starvation inside a bead
    for bead in rep["beads"]:
        assert abs(bead["speed_measured_mm_min"] / bead["speed_planned_mm_min"] - 1) < 0.03, json.dumps(bead)
        assert bead["starved_count"] == 0 and bead["motion_time_s"] > 0 and bead["still_count"] == 0
        assert abs(bead["length_measured_mm"] - bead["length_planned_mm"]) < 0.01 and bead["status"] == "done"
    assert rep["travel_speed"]["starved_beads"] == 0
    assert rep["started"].endswith("+00:00") and rep["ended"] >= rep["started"]
    assert rep["material"] == "inconel718-1.0mm" and rep["software_version"]
    assert [la["layer"] for la in rep["layers"]] == [0, 1] and rep["layers"][1]["wait_s"] is not None
    figs = rep["arc_time_figures"]
    # the plan's arc time, the deposited length at planned speed, and at the measured speed
    assert figs["agree"] is True, figs
    assert abs(figs["measured_s"] / figs["plan_s"] - 1) < 0.02
    assert abs(figs["arc_on_s"] / figs["measured_s"] - 1) < 0.05   # no ignition, no crater, no stand-still
    for png in ("layers.png", "process.png", "temperature.png", "defects.png"):
        assert (run_dir / png).stat().st_size > 1000

    out_csv = tmp_path / "x.csv"
    assert main(["report", str(run_dir), "--csv", str(out_csv), "--no-plots", "--json",
                 "--operator", "A. Welder"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["operator"] == "A. Welder" and summary["beads"] == 4 and summary["state"] == "complete"
    assert len(list(csv.DictReader(out_csv.open()))) == 4

    assert main(["runs", "--runs", str(tmp_path / "runs"), "--json"]) == 0
    runs = json.loads(capsys.readouterr().out)["runs"]
    assert [(r["dir"], r["state"], r["layers_done"]) for r in runs] == [(str(run_dir), "complete", 2)]


async def test_a_record_without_plots_has_its_numbers_and_cell_report_draws_them_later(tmp_path: Path,
                                                                                   capsys) -> None:
    """CELL_RECORD_PLOTS=0 (the tests' default, tests/conftest.py): report.json and beads.csv at the
    build's end, no PNG, and the message line says how to draw them."""
    job = small_job(n_layers=1)
    async with Cell(tmp_path, scale=20) as c:
        run_dir = c.ctl.open_job(job_from_dict(job))
        res = await c.ctl.start()
        msg = c.ctl.bus.latest.message
    assert res.state == "complete"
    rep = json.loads((run_dir / "report.json").read_text())
    assert rep["plots"] == [] and len(list(csv.DictReader((run_dir / "beads.csv").open()))) == 2
    assert not list(run_dir.glob("*.png"))
    assert "no plots" in msg and f"cell report {run_dir}" in msg, msg
    assert main(["report", str(run_dir), "--json"]) == 0
    assert {"layers.png", "process.png", "temperature.png", "defects.png"} <= {p.name for p in run_dir.glob("*.png")}
    assert json.loads((run_dir / "report.json").read_text())["beads"] == rep["beads"]


def test_report_of_a_directory_without_a_journal_is_one_error_line(tmp_path: Path, capsys) -> None:
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "journal.sqlite" in err and err.count("\n") == 1

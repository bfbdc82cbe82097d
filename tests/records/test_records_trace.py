"""Traceability (issue 39 item 1, docs/records.md): wire lot, gas and operator from cell.yaml or the
command, in the journal and in the record; a cell that requires a lot refuses a build without one
before any device is touched."""
from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest

from controller.cli.main import main
from tests.cells import small_job
from tests.records.lot_config import cell_yaml

pytestmark = pytest.mark.realtime  # `cell run --sim` on the wall clock (tests/conftest.py)


def test_a_cell_that_requires_a_lot_refuses_a_build_without_one_before_any_device(tmp_path: Path, capsys) -> None:
    jf = tmp_path / "job.json"
    jf.write_text(json.dumps(small_job(1)))
    cfg = cell_yaml(tmp_path, require_lot=True)
    runs = tmp_path / "runs"
    assert main(["run", str(jf), "--sim", "--cell-config", str(cfg), "--runs", str(runs), "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: no wire lot") and "--wire-lot" in err[0]
    assert not runs.exists()   # no run directory, no journal: nothing was started
    # a blank lot is no lot
    assert main(["run", str(jf), "--sim", "--cell-config", str(cfg), "--runs", str(runs), "--wire-lot", "  "]) == 2
    assert "records.require_lot" in capsys.readouterr().err


def test_lot_gas_and_operator_from_cell_yaml_and_the_command_are_in_the_journal_and_the_record(
        tmp_path: Path, capsys) -> None:
    jf = tmp_path / "job.json"
    jf.write_text(json.dumps(small_job(1)))
    # cell.yaml gives the gas and the operator; the command gives the lot and replaces the operator
    cfg = cell_yaml(tmp_path, require_lot=True, gas="Ar 4.6 (lot G-118)", operator="B. Shift")
    runs = tmp_path / "runs"
    assert main(["run", str(jf), "--sim", "--cell-config", str(cfg), "--runs", str(runs), "--json",
                 "--wire-lot", "HX-2291", "--operator", "A. Welder"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["state"] == "complete"
    rep = json.loads(Path(out["report"]).read_text())
    assert rep["wire_lot"] == "HX-2291" and rep["wire"]["lot"] == "HX-2291"
    assert rep["wire"]["alloy"] and rep["wire"]["diameter_mm"] == 1.0
    assert rep["gas"] == "Ar 4.6 (lot G-118)" and rep["operator"] == "A. Welder"
    assert rep["cell"] == "demo-cell" and len(rep["build_id"]) == 36
    assert [(t["run"], t["wire_lot"]) for t in rep["traceability"]] == [(1, "HX-2291")]
    db = sqlite3.connect(Path(out["run_dir"]) / "journal.sqlite")
    (msg,) = db.execute("SELECT message FROM events WHERE kind='trace'").fetchone()
    db.close()
    assert json.loads(msg) == {"run": 1, "cell": "demo-cell", "wire_lot": "HX-2291", "gas": "Ar 4.6 (lot G-118)",
                               "operator": "A. Welder"}
    # `cell runs` lists the lot and the operator
    assert main(["runs", "--runs", str(runs)]) == 0
    line = capsys.readouterr().out.strip()
    assert "lot HX-2291" in line and "operator A. Welder" in line
    # `cell report RUN_DIR` rewrites the record from the journal with the same trace
    assert main(["report", out["run_dir"], "--no-plots", "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert (again["wire_lot"], again["gas"], again["build_id"]) == ("HX-2291", "Ar 4.6 (lot G-118)", rep["build_id"])
